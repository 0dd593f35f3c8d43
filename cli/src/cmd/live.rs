//! `--serve`: the live endpoint of a run (docs/live-api.md), wired to its session and client.

use std::path::Path;
use std::sync::Arc;

use lightrig_host::client::{Client, Interrupt};
use lightrig_host::live::{Live, RunInfo};
use lightrig_host::session::{now_rfc3339, Session};
use lightrig_host::transport::Transport;
use lightrig_serve::Server;

use crate::error::{err, CliError, USAGE};

/// A run being served: its live state and the endpoint (which stops when this is dropped).
pub(crate) struct Served {
    pub live: Arc<Live>,
    /// Where, as printed.
    pub url: String,
    _server: Server,
}

/// Starts serving a run of `command` on `addr`, stopped through `interrupt`; prints where.
pub(crate) fn serve(
    addr: &str,
    command: &str,
    session: &Path,
    device: &str,
    interrupt: Arc<Interrupt>,
) -> Result<Served, CliError> {
    let run = RunInfo {
        command: command.to_string(),
        pid: std::process::id(),
        session: session.display().to_string(),
        device: device.to_string(),
        method: String::new(),
        started: now_rfc3339(),
        address: String::new(),
    };
    let live = Live::new(run, interrupt);
    let server = Server::start(addr, live.clone()).map_err(|e| err(USAGE, e.to_string()))?;
    let url = server.url();
    eprintln!("live: {url}");
    Ok(Served { live, url, _server: server })
}

impl Served {
    /// From now on the session's records and the client's state reach those watching.
    pub fn attach<T: Transport>(&self, session: &mut Session, client: &mut Client<T>) {
        let live = self.live.clone();
        session.set_tap(Some(Arc::new(move |json: &[u8]| live.record(json))));
        client.set_live(self.live.clone());
    }

    /// The run ended as `result` says (a finished session that misses frames has finished).
    pub fn ended(&self, result: &Result<(), CliError>) {
        self.live.ended(match result {
            Ok(()) => Ok(()),
            Err(e) if e.code == crate::error::INCOMPLETE => Ok(()),
            Err(e) => Err(e.message.clone()),
        });
    }
}
