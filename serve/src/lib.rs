//! The live endpoint of a running acquisition (docs/live-api.md): an HTTP + WebSocket API over
//! a run's [`Live`] state, and the page built on it. Every connection is served on a thread of
//! its own with bounded reads, writes and time; the acquisition only ever updates `Live`.
//!
//! - [`http`]: requests and answers.
//! - [`ws`]: the WebSocket feed.
//! - [`thumb`]: frame statistics and thumbnails.
//! - [`client`]: a minimal client (`lightrig stop --url`, the tests).

pub mod client;
pub mod http;
pub mod thumb;
pub mod ws;

use std::collections::BTreeMap;
use std::io;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use lightrig_host::live::{Live, LiveFrame};

use crate::http::{respond, respond_error, Request};

/// The API version served (`/api/v1/…`).
pub const API: u32 = 1;
/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 32;
/// How long one write to a client may take before the client is dropped.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(5);
/// The address `--serve` takes without one.
pub const DEFAULT_ADDR: &str = "127.0.0.1:7878";
/// How long a stop waits for the device's answer before answering.
pub const STOP_WAIT: Duration = Duration::from_secs(3);

/// The time limits of an endpoint ([`Server::start_with`]; [`Server::start`] takes these
/// defaults).
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// One write to a client ([`WRITE_TIMEOUT`]).
    pub write_timeout: Duration,
    /// A stop's wait for the device's answer ([`STOP_WAIT`]).
    pub stop_wait: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { write_timeout: WRITE_TIMEOUT, stop_wait: STOP_WAIT }
    }
}

const PAGE: &str = include_str!("../assets/index.html");
const SCRIPT: &str = include_str!("../assets/app.js");
const STYLE: &str = include_str!("../assets/style.css");

/// A frame's thumbnail as made, or why it could not be.
type Made = Arc<Result<thumb::Thumb, String>>;

/// What the connection threads share.
pub(crate) struct Shared {
    pub live: Arc<Live>,
    pub token: Option<String>,
    pub addr: SocketAddr,
    pub done: AtomicBool,
    pub connections: AtomicUsize,
    pub limits: Limits,
    /// The latest thumbnail of each camera, by the frame's `seq`.
    thumbs: Mutex<BTreeMap<u8, (u64, Made)>>,
}

impl Shared {
    /// The thumbnail of `frame`, made once and shared by every client.
    pub fn thumb(&self, frame: &LiveFrame) -> Made {
        if let Some((seq, t)) = self.thumbs.lock().unwrap_or_else(|p| p.into_inner()).get(&frame.camera) {
            if *seq == frame.seq {
                return t.clone();
            }
        }
        let made = Arc::new(thumb::make(frame, self.live.marks_spot()));
        self.thumbs.lock().unwrap_or_else(|p| p.into_inner()).insert(frame.camera, (frame.seq, made.clone()));
        made
    }

    /// FRAME (docs/live-api.md) of `frame`.
    pub fn frame_json(&self, frame: &LiveFrame) -> serde_json::Value {
        let mut v = serde_json::json!({
            "camera": frame.camera,
            "seq": frame.seq,
            "step": frame.step,
            "frame": frame.frame,
            "ext": frame.ext,
            "host_us": frame.host_us,
            "trigger": frame.trigger,
            "thumbnail": format!("/api/v1/frames/{}.png?seq={}", frame.camera, frame.seq),
        });
        match &*self.thumb(frame) {
            Ok(t) => {
                let s = &t.stats;
                let extra = serde_json::json!({
                    "width": s.width, "height": s.height, "channels": s.channels, "bits": s.bits,
                    "pixels": s.pixels, "clipped": s.clipped, "min": s.min, "max": s.max,
                    "histogram": s.histogram,
                    "spot": s.spot.map(|(x, y)| serde_json::json!({"x": x, "y": y})),
                });
                if let (Some(v), Some(e)) = (v.as_object_mut(), extra.as_object()) {
                    v.extend(e.clone());
                }
            }
            Err(why) => v["error"] = why.clone().into(),
        }
        v
    }
}

/// A running endpoint; it stops when dropped (WebSocket clients are sent `end` first).
pub struct Server {
    shared: Arc<Shared>,
    accept: Option<std::thread::JoinHandle<()>>,
}

impl Server {
    /// Serves `live` on `addr` (`127.0.0.1:0` for any free port). Loopback addresses are served
    /// without a token; any other needs the token made now ([`Server::token`]).
    pub fn start(addr: &str, live: Arc<Live>) -> io::Result<Server> {
        Server::start_with(addr, live, Limits::default())
    }

    /// [`Server::start`] with other time limits.
    pub fn start_with(addr: &str, live: Arc<Live>, limits: Limits) -> io::Result<Server> {
        let listener = TcpListener::bind(addr).map_err(|e| {
            io::Error::new(e.kind(), format!("--serve {addr}: {e} (choose another address or port)"))
        })?;
        let addr = listener.local_addr()?;
        let token = (!addr.ip().is_loopback()).then(new_token).transpose()?;
        let shared = Arc::new(Shared {
            live,
            token,
            addr,
            done: AtomicBool::new(false),
            connections: AtomicUsize::new(0),
            limits,
            thumbs: Mutex::new(BTreeMap::new()),
        });
        let url = url_of(addr, shared.token.as_deref());
        shared.live.set_address(&url);
        let s = shared.clone();
        let accept = std::thread::Builder::new()
            .name("lightrig-serve".into())
            .spawn(move || accept_loop(listener, s))?;
        Ok(Server { shared, accept: Some(accept) })
    }

    /// The address served.
    pub fn addr(&self) -> SocketAddr {
        self.shared.addr
    }

    /// The token requests need (`None` on loopback).
    pub fn token(&self) -> Option<&str> {
        self.shared.token.as_deref()
    }

    /// Connections being served now.
    pub fn connections(&self) -> usize {
        self.shared.connections.load(Ordering::SeqCst)
    }

    /// The page's address, with the token if there is one.
    pub fn url(&self) -> String {
        url_of(self.shared.addr, self.shared.token.as_deref())
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.shared.done.store(true, Ordering::SeqCst);
        // Wakes the accept loop, which then sees `done`.
        let _ = TcpStream::connect_timeout(&self.shared.addr, Duration::from_millis(200));
        if let Some(t) = self.accept.take() {
            let _ = t.join();
        }
        // Connection threads see `done` within their next turn; WebSockets say `end`.
        let until = Instant::now() + Duration::from_secs(1);
        while self.shared.connections.load(Ordering::SeqCst) > 0 && Instant::now() < until {
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

fn url_of(addr: SocketAddr, token: Option<&str>) -> String {
    match token {
        Some(t) => format!("http://{addr}/?token={t}"),
        None => format!("http://{addr}/"),
    }
}

fn new_token() -> io::Result<String> {
    let mut b = [0u8; 16];
    getrandom::getrandom(&mut b).map_err(|e| io::Error::other(format!("no random token: {e}")))?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

fn accept_loop(listener: TcpListener, shared: Arc<Shared>) {
    for stream in listener.incoming() {
        if shared.done.load(Ordering::SeqCst) {
            break;
        }
        let Ok(mut stream) = stream else { continue };
        let _ = stream.set_write_timeout(Some(shared.limits.write_timeout));
        if shared.connections.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
            shared.connections.fetch_sub(1, Ordering::SeqCst);
            let _ = stream.set_write_timeout(Some(Duration::from_millis(200)));
            let _ = respond_error(&mut stream, 503, "too many connections; close one and try again");
            continue;
        }
        let s = shared.clone();
        let spawned = std::thread::Builder::new().name("lightrig-serve-conn".into()).spawn(move || {
            let _ = serve_connection(stream, &s);
            s.connections.fetch_sub(1, Ordering::SeqCst);
        });
        if spawned.is_err() {
            shared.connections.fetch_sub(1, Ordering::SeqCst);
        }
    }
}

fn serve_connection(mut stream: TcpStream, shared: &Shared) -> io::Result<()> {
    let req = match http::read_request(&mut stream) {
        Ok(Some(r)) => r,
        Ok(None) => return Ok(()),
        Err(r) => return respond_error(&mut stream, r.status, &r.why),
    };
    if let Err((status, why)) = admit(&req, shared) {
        return respond_error(&mut stream, status, &why);
    }
    route(stream, &req, shared)
}

/// Who may ask (docs/live-api.md, "Who may connect").
fn admit(req: &Request, shared: &Shared) -> Result<(), (u16, String)> {
    let port = shared.addr.port();
    let host = req.header("host").unwrap_or("");
    match &shared.token {
        Some(token) => {
            let bearer = req.header("authorization").and_then(|a| a.strip_prefix("Bearer ")).map(str::trim);
            let given = bearer.or(req.param("token"));
            if !given.is_some_and(|g| constant_time_eq(g.as_bytes(), token.as_bytes())) {
                return Err((
                    401,
                    "this endpoint needs the token its run printed: ?token=… or Authorization: Bearer …"
                        .into(),
                ));
            }
        }
        None => {
            let ok = [format!("127.0.0.1:{port}"), format!("localhost:{port}"), format!("[::1]:{port}")];
            if !ok.iter().any(|h| h.eq_ignore_ascii_case(host)) {
                return Err((
                    403,
                    format!(
                        "Host {host:?} is not this loopback endpoint (127.0.0.1:{port} or localhost:{port})"
                    ),
                ));
            }
        }
    }
    if req.method == "POST" {
        if let Some(origin) = req.header("origin") {
            if !origin.strip_prefix("http://").is_some_and(|o| o.eq_ignore_ascii_case(host)) {
                return Err((403, format!("a page of {origin} may not command this run")));
            }
        }
    }
    Ok(())
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
}

fn json(stream: &mut TcpStream, status: u16, v: &serde_json::Value) -> io::Result<()> {
    respond(stream, status, "application/json", v.to_string().as_bytes())
}

fn route(mut stream: TcpStream, req: &Request, shared: &Shared) -> io::Result<()> {
    let live = &shared.live;
    let path = req.path.as_str();
    let get = req.method == "GET" || req.method == "HEAD";
    match (req.method.as_str(), path) {
        (_, "/") if get => respond(&mut stream, 200, "text/html; charset=utf-8", PAGE.as_bytes()),
        (_, "/app.js") if get => {
            respond(&mut stream, 200, "text/javascript; charset=utf-8", SCRIPT.as_bytes())
        }
        (_, "/style.css") if get => respond(&mut stream, 200, "text/css; charset=utf-8", STYLE.as_bytes()),
        (_, "/api/v1/status") if get => json(&mut stream, 200, &live.status()),
        (_, "/api/v1/journal") if get => {
            let since = req.param("since").and_then(|s| s.parse().ok()).unwrap_or(0);
            let limit = req.param("limit").and_then(|s| s.parse().ok()).unwrap_or(1000).min(1000);
            let (first, next, records) = live.records(since, limit);
            // The records' JSON as written, not parsed again.
            let mut body = format!("{{\"first\":{first},\"next\":{next},\"records\":[");
            for (i, (seq, r)) in records.iter().enumerate() {
                if i > 0 {
                    body.push(',');
                }
                body.push_str(&format!("{{\"seq\":{seq},\"record\":{r}}}"));
            }
            body.push_str("]}");
            respond(&mut stream, 200, "application/json", body.as_bytes())
        }
        (_, "/api/v1/frames") if get => {
            live.watch();
            let cameras: Vec<serde_json::Value> =
                live.frames().iter().map(|f| shared.frame_json(f)).collect();
            json(&mut stream, 200, &serde_json::json!({"cameras": cameras}))
        }
        (_, p) if get && p.starts_with("/api/v1/frames/") && p.ends_with(".png") => {
            live.watch();
            let camera = p["/api/v1/frames/".len()..p.len() - 4].parse::<u8>().ok();
            let frame = camera.and_then(|c| live.frames().into_iter().find(|f| f.camera == c));
            match frame {
                None => respond_error(&mut stream, 404, "no frame of that camera yet"),
                Some(f) => match &*shared.thumb(&f) {
                    Ok(t) => respond(&mut stream, 200, "image/png", &t.png),
                    Err(why) => respond_error(&mut stream, 500, why),
                },
            }
        }
        (_, "/api/v1/ws") if get => ws::serve(stream, req, shared),
        ("POST", "/api/v1/stop") => {
            live.stop();
            let until = Instant::now() + shared.limits.stop_wait;
            while !live.stop_state().1 && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(10));
            }
            let (requested, sent, answered) = live.stop_state();
            let message = if answered {
                "stopped: the device answered the emergency stop"
            } else if sent {
                "unconfirmed: the stop was sent, the device did not answer it"
            } else {
                "unconfirmed: the stop is asked for; the run has not reached the device yet"
            };
            let stop = serde_json::json!({"requested": requested, "sent": sent, "answered": answered});
            json(&mut stream, 200, &serde_json::json!({"ok": true, "stop": stop, "message": message}))
        }
        ("POST", "/api/v1/pause") | ("POST", "/api/v1/resume") => {
            let r = if path.ends_with("pause") { live.pause() } else { live.resume() };
            match r {
                Ok(state) => json(&mut stream, 200, &serde_json::json!({"ok": true, "state": state})),
                Err(why) => respond_error(&mut stream, 409, &why),
            }
        }
        (_, "/api/v1/stop" | "/api/v1/pause" | "/api/v1/resume") => {
            respond_error(&mut stream, 405, "commands are POST requests")
        }
        _ if !get && req.method != "POST" => respond_error(&mut stream, 405, "GET or POST"),
        _ => respond_error(
            &mut stream,
            404,
            &format!("no {path} here; the API is under /api/v1/ (docs/live-api.md)"),
        ),
    }
}
