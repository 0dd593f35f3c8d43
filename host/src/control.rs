//! A running acquisition's control socket. The process that holds a device's port is the only
//! one that can talk to the device (the port is opened exclusively), so `lightrig stop` from
//! another terminal reaches the device through that process: a Unix socket named after the
//! port, in a directory only this user can enter. One request line, one answer line:
//!
//! - `stop`: the run sends `EmergencyStop` at its next turn of the link (as Ctrl-C does); the
//!   answer says whether the device answered it.
//! - `status`: what the run is (`lightrig acquire`, its pid, the device, the session).
//!
//! Requests are at most [`MAX_REQUEST`] bytes and must arrive within a second: a client that
//! connects and says nothing cannot hold up the next one for longer than that, nor the run at
//! all (the socket is served on a thread of its own).

use std::io::{self, BufRead, BufReader, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::client::Interrupt;

/// The longest request line taken, bytes.
pub const MAX_REQUEST: u64 = 64;
/// How long a client has to send its request, and to read the answer.
const CLIENT_TIMEOUT: Duration = Duration::from_secs(1);
/// How long a `stop` waits for the run to say the device answered.
const STOP_WAIT: Duration = Duration::from_secs(3);

/// Where the sockets live: `$XDG_RUNTIME_DIR/lightrig`, else `/tmp/lightrig-UID`; created
/// mode 0700 (only this user can reach a run through it).
pub fn socket_dir() -> PathBuf {
    match std::env::var_os("XDG_RUNTIME_DIR").map(PathBuf::from) {
        Some(d) if d.is_absolute() && d.is_dir() => d.join("lightrig"),
        _ => std::env::temp_dir().join(format!("lightrig-{}", uid())),
    }
}

fn uid() -> u32 {
    use std::os::unix::fs::MetadataExt;
    // /proc/self belongs to this process's user: its uid without a libc call.
    std::fs::metadata("/proc/self").map(|m| m.uid()).unwrap_or(0)
}

/// The names a port is known by: as given (made absolute, links not followed: a pty's stable
/// link) and where it leads now (`/dev/pts/7`). A run serves both; `stop` tries both.
pub fn port_keys(port: &str) -> Vec<String> {
    let given = std::path::absolute(port).unwrap_or_else(|_| PathBuf::from(port));
    let mut keys = vec![given.display().to_string()];
    if let Ok(real) = std::fs::canonicalize(port) {
        let real = real.display().to_string();
        if real != keys[0] {
            keys.push(real);
        }
    }
    keys
}

/// The socket for the port known as `key` (a hash: ports' paths may be longer than a socket
/// path may be).
pub fn socket_for(key: &str) -> PathBuf {
    // FNV-1a, 64 bits: stable across builds and platforms.
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in key.bytes() {
        h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    socket_dir().join(format!("port-{h:016x}.sock"))
}

/// A run's control socket, served until dropped (the socket files are then removed).
pub struct ControlServer {
    paths: Vec<PathBuf>,
    done: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl ControlServer {
    /// Serves `stop` and `status` for the port known by `keys` ([`port_keys`]): `stop` asks
    /// `interrupt`, `status` answers `about`. A socket file left by a run that died is
    /// replaced; one a live run still answers on is an error naming that run.
    pub fn serve(keys: &[String], interrupt: Arc<Interrupt>, about: String) -> io::Result<ControlServer> {
        let dir = socket_dir();
        make_private_dir(&dir)?;
        let done = Arc::new(AtomicBool::new(false));
        let mut server = ControlServer { paths: Vec::new(), done: done.clone(), threads: Vec::new() };
        for key in keys {
            let path = socket_for(key);
            if path.symlink_metadata().is_ok() {
                if let Ok(Some(other)) = ask(&path, "status") {
                    return Err(io::Error::new(
                        io::ErrorKind::AddrInUse,
                        format!("{key} is already served by another run: {other}"),
                    ));
                }
                std::fs::remove_file(&path)?;
            }
            let listener = UnixListener::bind(&path)
                .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))?;
            server.paths.push(path);
            let (interrupt, about, done) = (interrupt.clone(), about.clone(), done.clone());
            server.threads.push(std::thread::spawn(move || {
                for stream in listener.incoming() {
                    if done.load(Ordering::SeqCst) {
                        break;
                    }
                    if let Ok(s) = stream {
                        let _ = answer(s, &interrupt, &about);
                    }
                }
            }));
        }
        Ok(server)
    }

    /// The socket files it serves.
    pub fn paths(&self) -> &[PathBuf] {
        &self.paths
    }
}

impl Drop for ControlServer {
    fn drop(&mut self) {
        self.done.store(true, Ordering::SeqCst);
        for p in &self.paths {
            // Wakes the thread blocked in accept, which then sees `done`.
            let _ = UnixStream::connect(p);
            let _ = std::fs::remove_file(p);
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

fn make_private_dir(dir: &Path) -> io::Result<()> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    match std::fs::DirBuilder::new().mode(0o700).create(dir) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
            // Another user's directory (or a link planted in /tmp) is not ours to serve from.
            let m = dir.symlink_metadata()?;
            if !m.is_dir() || m.uid() != uid() || m.permissions().mode() & 0o077 != 0 {
                return Err(io::Error::new(
                    io::ErrorKind::PermissionDenied,
                    format!(
                        "{}: not a private directory of this user (mode {:o}); remove it or set \
                         XDG_RUNTIME_DIR",
                        dir.display(),
                        m.permissions().mode() & 0o7777
                    ),
                ));
            }
            Ok(())
        }
        Err(e) => Err(io::Error::new(e.kind(), format!("{}: {e}", dir.display()))),
    }
}

/// One client: its request line, then the answer.
fn answer(stream: UnixStream, interrupt: &Interrupt, about: &str) -> io::Result<()> {
    stream.set_read_timeout(Some(CLIENT_TIMEOUT))?;
    stream.set_write_timeout(Some(CLIENT_TIMEOUT))?;
    let mut line = String::new();
    BufReader::new((&stream).take(MAX_REQUEST)).read_line(&mut line)?;
    let reply = match line.trim() {
        "stop" => {
            interrupt.request();
            let until = Instant::now() + STOP_WAIT;
            while !interrupt.stopped() && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(10));
            }
            if interrupt.answered() {
                format!("stopped: {about}: the device answered the emergency stop")
            } else if interrupt.stopped() {
                format!("unconfirmed: {about}: the stop was sent, the device did not answer it")
            } else {
                format!("unconfirmed: {about}: the stop is asked for; the run has not reached the device yet")
            }
        }
        "status" => format!("running: {about}"),
        other => format!("error: unknown request {other:?}; say `stop` or `status`"),
    };
    (&stream).write_all(format!("{reply}\n").as_bytes())
}

/// Sends `request` to the run serving `socket`; `Ok(None)` if no run serves it (no socket, or
/// one a run that died left behind).
pub fn ask(socket: &Path, request: &str) -> io::Result<Option<String>> {
    let stream = match UnixStream::connect(socket) {
        Ok(s) => s,
        Err(e) if matches!(e.kind(), io::ErrorKind::NotFound | io::ErrorKind::ConnectionRefused) => {
            return Ok(None)
        }
        Err(e) => return Err(io::Error::new(e.kind(), format!("{}: {e}", socket.display()))),
    };
    stream.set_read_timeout(Some(STOP_WAIT + CLIENT_TIMEOUT))?;
    stream.set_write_timeout(Some(CLIENT_TIMEOUT))?;
    (&stream).write_all(format!("{request}\n").as_bytes())?;
    let mut line = String::new();
    BufReader::new((&stream).take(4096)).read_line(&mut line)?;
    Ok(Some(line.trim_end().to_string()))
}

/// Asks the run that holds `port`, if one does, to `request`.
pub fn ask_port(port: &str, request: &str) -> io::Result<Option<String>> {
    for key in port_keys(port) {
        if let Some(reply) = ask(&socket_for(&key), request)? {
            return Ok(Some(reply));
        }
    }
    Ok(None)
}

/// Every run of this user that serves a control socket: its socket and `status` answer.
pub fn running() -> Vec<(PathBuf, String)> {
    let Ok(entries) = std::fs::read_dir(socket_dir()) else { return Vec::new() };
    let mut out: Vec<(PathBuf, String)> = Vec::new();
    for p in entries.flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|x| x == "sock")) {
        match ask(&p, "status") {
            Ok(Some(s)) => out.push((p, s)),
            // Left by a run that ended without tidying up (killed, or its Ctrl-C timer).
            Ok(None) => {
                let _ = std::fs::remove_file(&p);
            }
            Err(_) => {}
        }
    }
    out.sort();
    // A run serves its port under two names (the link and where it leads): once each.
    let mut seen = std::collections::HashSet::new();
    out.retain(|(_, status)| seen.insert(status.clone()));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn private_runtime() -> PathBuf {
        // Each test process its own socket directory (the tests share XDG_RUNTIME_DIR).
        let d = std::env::temp_dir().join(format!("lightrig-control-test-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        std::env::set_var("XDG_RUNTIME_DIR", &d);
        d
    }

    #[test]
    fn stop_through_the_socket_asks_the_interrupt_and_says_whether_the_device_answered() {
        let _d = private_runtime();
        let interrupt = Arc::new(Interrupt::default());
        let keys = vec!["/dev/test-port-a".to_string()];
        let server = ControlServer::serve(&keys, interrupt.clone(), "test run".into()).unwrap();
        assert_eq!(ask(&socket_for(&keys[0]), "status").unwrap().as_deref(), Some("running: test run"));
        assert!(!interrupt.requested(), "status asks nothing of the run");
        let bad = ask(&socket_for(&keys[0]), "launch").unwrap().unwrap();
        assert!(bad.starts_with("error: unknown request \"launch\""), "{bad}");
        // Nobody drives a link here: the stop is asked for, not confirmed.
        let reply = ask(&socket_for(&keys[0]), "stop").unwrap().unwrap();
        assert!(interrupt.requested());
        assert!(reply.starts_with("unconfirmed: test run"), "{reply}");
        let listed = running();
        assert!(listed.iter().any(|(_, s)| s == "running: test run"), "{listed:?}");
        // A dead run's socket beside it is tidied away by the listing.
        let dead = socket_for("/dev/test-port-dead");
        drop(UnixListener::bind(&dead).unwrap());
        let listed = running();
        assert!(listed.iter().all(|(p, _)| *p != dead) && !dead.exists(), "{listed:?}");
        let paths = server.paths().to_vec();
        drop(server);
        assert!(paths.iter().all(|p| !p.exists()), "the socket files go with the run");
        assert_eq!(ask(&paths[0], "status").unwrap(), None);
    }

    #[test]
    fn a_client_that_says_nothing_does_not_hold_up_the_next() {
        let _d = private_runtime();
        let interrupt = Arc::new(Interrupt::default());
        let keys = vec!["/dev/test-port-b".to_string()];
        let _server = ControlServer::serve(&keys, interrupt, "quiet test".into()).unwrap();
        let silent = UnixStream::connect(socket_for(&keys[0])).unwrap();
        // Answered once the silent one's second is up, within `ask`'s own read timeout (an
        // error, failing the test, if the server waited on the silent client for ever).
        assert_eq!(ask(&socket_for(&keys[0]), "status").unwrap().as_deref(), Some("running: quiet test"));
        drop(silent);
    }

    #[test]
    fn a_socket_left_by_a_dead_run_is_replaced_and_a_live_one_refused() {
        let _d = private_runtime();
        let key = "/dev/test-port-c".to_string();
        make_private_dir(&socket_dir()).unwrap();
        // A dead run's socket: bound, then its listener gone.
        drop(UnixListener::bind(socket_for(&key)).unwrap());
        let first = ControlServer::serve(std::slice::from_ref(&key), Arc::default(), "first".into()).unwrap();
        let e = ControlServer::serve(std::slice::from_ref(&key), Arc::default(), "second".into())
            .err()
            .expect("a live run's socket is not taken over");
        assert!(e.to_string().contains("already served by another run: running: first"), "{e}");
        drop(first);
    }
}
