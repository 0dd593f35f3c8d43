//! The WebSocket feed (`/api/v1/ws`): the journal's records as they are written, the status
//! while it changes, each camera's latest frame, and `end`. Each client on its own thread with
//! its own cursor into the records [`Live`](lightrig_host::live::Live) keeps: a client that
//! falls behind is told `lagged`, one that stops reading is dropped at the write timeout; the
//! acquisition never waits for either.

use std::collections::BTreeMap;
use std::io::{self, ErrorKind};
use std::net::TcpStream;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use tungstenite::protocol::{Role, WebSocketConfig};
use tungstenite::{Message, WebSocket};

use crate::http::{respond_error, Request};
use crate::Shared;

/// The status is sent this often while it changes…
const STATUS_EVERY: Duration = Duration::from_millis(500);
/// …and this often when it does not.
const STATUS_IDLE: Duration = Duration::from_secs(5);
/// Records sent per turn at most (the rest at the next).
const RECORDS_PER_TURN: usize = 256;
/// Messages from the client are taken up to this size (it has nothing to say).
const MAX_INCOMING: usize = 4096;

/// Upgrades `stream` (the request `req` asked to) and feeds it until the run ends, the client
/// goes, or it stops reading.
pub(crate) fn serve(mut stream: TcpStream, req: &Request, shared: &Shared) -> io::Result<()> {
    let upgrade = req.header("upgrade").is_some_and(|u| u.eq_ignore_ascii_case("websocket"));
    let Some(key) = req.header("sec-websocket-key").filter(|_| upgrade) else {
        return respond_error(&mut stream, 400, "a WebSocket upgrade request is expected here");
    };
    if req.header("sec-websocket-version") != Some("13") {
        return respond_error(&mut stream, 400, "WebSocket version 13 is spoken here");
    }
    let accept = tungstenite::handshake::derive_accept_key(key.as_bytes());
    let head = format!(
        "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Accept: {accept}\r\n\r\n"
    );
    io::Write::write_all(&mut stream, head.as_bytes())?;
    // Reads wait briefly (the loop below has work to do); writes as long as WRITE_TIMEOUT.
    stream.set_read_timeout(Some(Duration::from_millis(20)))?;
    let config =
        WebSocketConfig::default().max_message_size(Some(MAX_INCOMING)).max_frame_size(Some(MAX_INCOMING));
    let mut ws = WebSocket::from_raw_socket(stream, Role::Server, Some(config));
    let live = &shared.live;
    live.socket(true);
    let since = req.param("since").and_then(|s| s.parse().ok());
    let result = feed(&mut ws, shared, since);
    live.socket(false);
    let _ = ws.close(None);
    let _ = ws.flush();
    result
}

fn send(ws: &mut WebSocket<TcpStream>, text: String) -> io::Result<()> {
    ws.send(Message::text(text)).map_err(to_io)
}

fn to_io(e: tungstenite::Error) -> io::Error {
    match e {
        tungstenite::Error::Io(e) => e,
        other => io::Error::other(other.to_string()),
    }
}

fn typed(kind: &str, mut v: serde_json::Value) -> String {
    if let Some(o) = v.as_object_mut() {
        o.insert("type".into(), kind.into());
    }
    v.to_string()
}

fn feed(ws: &mut WebSocket<TcpStream>, shared: &Shared, since: Option<u64>) -> io::Result<()> {
    let live = &shared.live;
    let status = live.status();
    let mut cursor = since.unwrap_or_else(|| status["journal"]["next"].as_u64().unwrap_or(0));
    send(ws, serde_json::json!({"type": "hello", "api": crate::API, "status": status}).to_string())?;
    let mut sent_version = live.version();
    let mut sent_at = Instant::now();
    let mut frames_sent: BTreeMap<u8, u64> = BTreeMap::new();
    loop {
        // What the client says is read only to see it close (and to answer its pings).
        match ws.read() {
            Ok(Message::Close(_)) => return Ok(()),
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => return Ok(()),
            Err(e) => return Err(to_io(e)),
        }
        let version = live.version();
        let (first, next, records) = live.records(cursor, RECORDS_PER_TURN);
        if cursor < first {
            send(
                ws,
                serde_json::json!({"type": "lagged", "skipped": first - cursor, "next": first}).to_string(),
            )?;
            cursor = first;
        }
        for (seq, r) in &records {
            send(ws, format!("{{\"type\":\"record\",\"seq\":{seq},\"record\":{r}}}"))?;
            cursor = seq + 1;
        }
        for f in live.frames() {
            if frames_sent.get(&f.camera) != Some(&f.seq) {
                frames_sent.insert(f.camera, f.seq);
                send(ws, typed("frame", shared.frame_json(&f)))?;
            }
        }
        let ended = live.has_ended() || shared.done.load(Ordering::SeqCst);
        let due = if version != sent_version { STATUS_EVERY } else { STATUS_IDLE };
        if sent_at.elapsed() >= due || ended && cursor >= next {
            send(ws, typed("status", live.status()))?;
            sent_version = version;
            sent_at = Instant::now();
        }
        if ended && cursor >= next {
            let (state, reason) = live.state_word();
            send(ws, serde_json::json!({"type": "end", "state": state, "reason": reason}).to_string())?;
            return Ok(());
        }
        if records.len() < RECORDS_PER_TURN {
            live.wait_change(version, Duration::from_millis(100));
        }
    }
}
