//! Fsyncing the journal on a thread of its own, for event records: a device event is journaled
//! from the link loop as it arrives, and an fsync on a slow or busy disk (hundreds of ms) would
//! hold that loop, and a real-time device's heartbeat, up. The event's line is written at once;
//! only waiting for it to be durable moves here. Every other record is still fsynced before
//! `append` returns, which also makes every event before it durable.

use std::fs::File;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{channel, Sender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// The journal's background fsync.
pub(super) struct Syncer {
    requests: Option<Sender<()>>,
    thread: Option<JoinHandle<()>>,
    failed: Arc<Mutex<Option<String>>>,
    /// Extra time every fsync takes, µs (a simulated slow disk; 0: none).
    delay_us: Arc<AtomicU64>,
}

impl Syncer {
    /// Fsyncs `journal` (a handle of the session's journal file) on request.
    pub(super) fn new(journal: File) -> Syncer {
        let (requests, inbox) = channel::<()>();
        let failed = Arc::new(Mutex::new(None));
        let delay_us = Arc::new(AtomicU64::new(0));
        let (f, d) = (failed.clone(), delay_us.clone());
        let thread = std::thread::spawn(move || {
            while inbox.recv().is_ok() {
                // Requests that came meanwhile are served by this one fsync.
                while inbox.try_recv().is_ok() {}
                slow_disk(&d);
                if let Err(e) = journal.sync_data() {
                    *f.lock().expect("not poisoned") = Some(format!("fsync of the journal failed: {e}"));
                    return;
                }
            }
        });
        Syncer { requests: Some(requests), thread: Some(thread), failed, delay_us }
    }

    /// Asks for an fsync; returns at once.
    pub(super) fn request(&self) {
        if let Some(r) = &self.requests {
            let _ = r.send(());
        }
    }

    /// Why a background fsync failed, if one did.
    pub(super) fn failure(&self) -> Option<String> {
        self.failed.lock().expect("not poisoned").clone()
    }

    /// The extra time each fsync takes.
    pub(super) fn delay(&self) -> Arc<AtomicU64> {
        self.delay_us.clone()
    }
}

/// Waits the simulated slow disk's extra time, if any.
pub(super) fn slow_disk(delay_us: &AtomicU64) {
    let us = delay_us.load(Ordering::Relaxed);
    if us > 0 {
        std::thread::sleep(Duration::from_micros(us));
    }
}

impl Drop for Syncer {
    fn drop(&mut self) {
        drop(self.requests.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
