//! A simulated tunable filter on a pseudo-terminal, for the virtual bispectral rig and tests:
//! it speaks [`lightrig_host::filter::CommandSet::default`]'s placeholder command set
//! (`W {nm}` and a carriage return; `OK` or `ERR …`), takes `settle` to tune (a liquid
//! crystal's switching time), refuses wavelengths outside its range, and keeps every wavelength
//! it was tuned to, in order.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use serialport::{SerialPort, TTYPort};

/// A filter serving on its own thread until dropped.
pub struct PtyFilter {
    path: PathBuf,
    tuned: Arc<Mutex<Vec<f64>>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl PtyFilter {
    /// A filter covering `range_nm` that takes `settle` per change; `silent`: it never answers
    /// (a filter switched off, or on the wrong port).
    pub fn start(range_nm: (f64, f64), settle: Duration, silent: bool) -> std::io::Result<Self> {
        let (mut master, slave) = TTYPort::pair().map_err(std::io::Error::other)?;
        let path =
            slave.name().map(PathBuf::from).ok_or_else(|| std::io::Error::other("the pty has no name"))?;
        master.set_timeout(Duration::from_millis(20)).map_err(std::io::Error::other)?;
        let tuned = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let (t, s) = (tuned.clone(), stop.clone());
        let thread = std::thread::spawn(move || {
            let _slave = slave; // keeps the master readable while no client has the port open
            let mut line = Vec::new();
            let mut buf = [0u8; 64];
            while !s.load(Ordering::SeqCst) {
                let n = match master.read(&mut buf) {
                    Ok(n) => n,
                    Err(_) => continue,
                };
                for &b in &buf[..n] {
                    if b != b'\r' && b != b'\n' {
                        line.push(b);
                        continue;
                    }
                    let text = String::from_utf8_lossy(&line).trim().to_string();
                    line.clear();
                    if text.is_empty() || silent {
                        continue;
                    }
                    let reply = match text.strip_prefix("W ").and_then(|v| v.trim().parse::<f64>().ok()) {
                        Some(nm) if (range_nm.0..=range_nm.1).contains(&nm) => {
                            std::thread::sleep(settle);
                            t.lock().expect("not poisoned").push(nm);
                            "OK\r".to_string()
                        }
                        Some(nm) => format!("ERR {nm} nm out of range\r"),
                        None => format!("ERR unknown command {text:?}\r"),
                    };
                    let _ = master.write_all(reply.as_bytes());
                }
            }
        });
        Ok(PtyFilter { path, tuned, stop, thread: Some(thread) })
    }

    /// The port's path (`/dev/pts/N`).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Every wavelength it was tuned to, in order.
    pub fn tuned(&self) -> Vec<f64> {
        self.tuned.lock().expect("not poisoned").clone()
    }
}

impl Drop for PtyFilter {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
