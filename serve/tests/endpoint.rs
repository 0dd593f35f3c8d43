//! The endpoint against a `Live` state filled by hand: what each route answers, who is let in,
//! the limits, and the WebSocket feed, including a client that never reads. The network is
//! real (loopback); every wait is bounded and ends on what is awaited, not on a fixed time.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};

use lightrig_host::acquire::Captured;
use lightrig_host::client::Interrupt;
use lightrig_host::live::{Live, RunInfo};
use lightrig_imaging::io::{write_png, BitDepth, Encoding, Image};
use lightrig_serve::client::{parse_answer, Endpoint};
use lightrig_serve::{Limits, Server};
use tungstenite::Message;

fn live(method: &str) -> (Arc<Live>, Arc<Interrupt>) {
    let interrupt = Arc::new(Interrupt::default());
    let run = RunInfo {
        command: "acquire".into(),
        method: method.into(),
        session: "runs/x".into(),
        ..RunInfo::default()
    };
    (Live::new(run, interrupt.clone()), interrupt)
}

fn quick() -> Limits {
    Limits { write_timeout: Duration::from_millis(300), stop_wait: Duration::from_millis(100) }
}

fn endpoint(server: &Server) -> Endpoint {
    Endpoint::parse(&server.url(), None).unwrap()
}

/// Sends raw bytes, returns the status and body.
fn raw(server: &Server, bytes: &[u8]) -> (u16, String) {
    let mut s = TcpStream::connect(server.addr()).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let _ = s.write_all(bytes);
    let mut answer = Vec::new();
    let _ = s.read_to_end(&mut answer);
    let (status, body) = parse_answer(&answer).expect("an HTTP answer");
    (status, String::from_utf8_lossy(&body).into_owned())
}

fn get(server: &Server, path: &str, host: &str, extra: &str) -> (u16, String) {
    raw(server, format!("GET {path} HTTP/1.1\r\nHost: {host}\r\n{extra}\r\n").as_bytes())
}

/// A 16-bit grey PNG frame, `w` x `h`, of values `f(x, y)` in [0, 1].
fn png_frame(dir: &std::path::Path, w: u32, h: u32, f: impl Fn(u32, u32) -> f32) -> Vec<u8> {
    let path = dir.join("frame.png");
    let image = Image::from_fn(w, h, 1, |x, y, _| f(x, y)).with_encoding(Encoding::Srgb);
    write_png(&path, &image, BitDepth::Sixteen).unwrap();
    std::fs::read(path).unwrap()
}

fn scratch(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("lightrig-serve-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn captured(camera: u8, frame: u32, data: Vec<u8>) -> Captured {
    Captured {
        camera,
        frame: Some(frame),
        ext: "png".into(),
        data,
        host_us: 1.0,
        before_step: false,
        stamp: None,
    }
}

#[test]
fn status_journal_and_frames_answer_what_the_run_holds() {
    let (live, _) = live("disco");
    let server = Server::start_with("127.0.0.1:0", live.clone(), quick()).unwrap();
    let e = endpoint(&server);
    for i in 0..5 {
        live.record(format!("{{\"type\":\"Test\",\"n\":{i}}}").as_bytes());
    }
    let (code, status) = e.get_json("/api/v1/status").unwrap();
    assert_eq!(code, 200);
    assert_eq!(status["api"], 1);
    assert_eq!(status["state"], "starting");
    assert_eq!(status["run"]["session"], "runs/x");
    assert_eq!(status["run"]["address"], server.url());
    assert_eq!(status["journal"]["next"], 5);
    let (_, j) = e.get_json("/api/v1/journal?since=3").unwrap();
    assert_eq!((j["first"].as_u64(), j["next"].as_u64()), (Some(0), Some(5)));
    let got: Vec<(u64, u64)> = j["records"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["seq"].as_u64().unwrap(), r["record"]["n"].as_u64().unwrap()))
        .collect();
    assert_eq!(got, vec![(3, 3), (4, 4)]);

    // No frame before someone watches; reading the frames is watching.
    let (_, f) = e.get_json("/api/v1/frames").unwrap();
    assert_eq!(f["cameras"], serde_json::json!([]));
    assert_eq!(get(&server, "/api/v1/frames/0.png", &server.addr().to_string(), "").0, 404);
    // A laser spot at (20, 10) of a 64 x 32 frame, one pixel saturated.
    let dir = scratch("frames");
    let data = png_frame(&dir, 64, 32, |x, y| if (x, y) == (20, 10) { 1.0 } else { 0.01 });
    live.arrived(&[captured(0, 3, data)]);
    let (_, f) = e.get_json("/api/v1/frames").unwrap();
    let c = &f["cameras"][0];
    assert_eq!((c["camera"].as_u64(), c["frame"].as_u64(), c["seq"].as_u64()), (Some(0), Some(3), Some(1)));
    assert_eq!(
        (c["width"].as_u64(), c["height"].as_u64(), c["bits"].as_u64()),
        (Some(64), Some(32), Some(16))
    );
    assert_eq!((c["pixels"].as_u64(), c["clipped"].as_u64()), (Some(2048), Some(1)));
    assert_eq!((c["spot"]["x"].as_f64(), c["spot"]["y"].as_f64()), (Some(20.5), Some(10.5)));
    assert_eq!(c["thumbnail"], "/api/v1/frames/0.png?seq=1");
    let (code, body) = e.request("GET", "/api/v1/frames/0.png?seq=1", None, Duration::from_secs(5)).unwrap();
    assert_eq!(code, 200);
    let thumb = image::load_from_memory(&body).unwrap();
    assert_eq!((thumb.width(), thumb.height()), (64, 32));
    assert_eq!(thumb.to_luma8().get_pixel(20, 10).0, [255]);
    // The page and its parts.
    let (code, page) = e.request("GET", "/", None, Duration::from_secs(5)).unwrap();
    assert_eq!(code, 200);
    let page = String::from_utf8(page).unwrap();
    for id in [
        "id=\"state\"",
        "id=\"progress\"",
        "id=\"eta\"",
        "id=\"stop\"",
        "id=\"pause\"",
        "id=\"resume\"",
        "id=\"log\"",
    ] {
        assert!(page.contains(id), "the page has {id}");
    }
    assert_eq!(e.request("GET", "/app.js", None, Duration::from_secs(5)).unwrap().0, 200);
    assert_eq!(e.request("GET", "/style.css", None, Duration::from_secs(5)).unwrap().0, 200);
    let (code, v) = e.get_json("/api/v2/status").unwrap();
    assert_eq!(code, 404);
    assert!(v["error"].as_str().unwrap().contains("/api/v1/"), "{v}");
    assert_eq!(e.get_json("/api/v1/stop").unwrap().0, 405, "commands are POSTs");
}

#[test]
fn commands_pause_resume_and_stop_the_run() {
    let (live, interrupt) = live("lls");
    let server = Server::start_with("127.0.0.1:0", live.clone(), quick()).unwrap();
    let e = endpoint(&server);
    live.started();
    let (code, v) = e.post_json("/api/v1/pause").unwrap();
    assert_eq!((code, v["state"].as_str()), (200, Some("pausing")));
    assert!(live.pause_requested());
    assert_eq!(e.get_json("/api/v1/status").unwrap().1["state"], "pausing");
    let (code, v) = e.post_json("/api/v1/resume").unwrap();
    assert_eq!((code, v["state"].as_str()), (200, Some("running")));
    assert!(!live.pause_requested());
    // Nobody drives a device here: the stop is asked for, not sent.
    let (code, v) = e.post_json("/api/v1/stop").unwrap();
    assert_eq!(code, 200);
    assert!(interrupt.requested());
    assert_eq!(v["stop"], serde_json::json!({"requested": true, "sent": false, "answered": false}));
    assert!(v["message"].as_str().unwrap().starts_with("unconfirmed"), "{v}");
    let (code, v) = e.post_json("/api/v1/pause").unwrap();
    assert_eq!(code, 409);
    assert!(v["error"].as_str().unwrap().contains("emergency-stopped"), "{v}");
}

#[test]
fn loopback_refuses_other_hosts_and_other_sites_commands() {
    let (live, interrupt) = live("lls");
    let server = Server::start_with("127.0.0.1:0", live, quick()).unwrap();
    let port = server.addr().port();
    assert_eq!(get(&server, "/api/v1/status", &format!("localhost:{port}"), "").0, 200);
    // DNS rebinding: a name that now resolves to 127.0.0.1.
    let (code, body) = get(&server, "/api/v1/status", &format!("rebound.example:{port}"), "");
    assert_eq!(code, 403);
    assert!(body.contains("not this loopback endpoint"), "{body}");
    let host = format!("127.0.0.1:{port}");
    let post = |origin: &str| {
        raw(
            &server,
            format!(
                "POST /api/v1/stop HTTP/1.1\r\nHost: {host}\r\nOrigin: {origin}\r\nContent-Length: 0\r\n\r\n"
            )
            .as_bytes(),
        )
    };
    let (code, body) = post("http://evil.example");
    assert_eq!(code, 403, "{body}");
    assert!(!interrupt.requested(), "another site's page pressed nothing");
    assert_eq!(post(&format!("http://{host}")).0, 200, "the page's own origin may");
    assert!(interrupt.requested());
}

#[test]
fn off_loopback_every_request_needs_the_token() {
    let (live, _) = live("lls");
    let server = Server::start_with("0.0.0.0:0", live, quick()).unwrap();
    let token = server.token().expect("a token off loopback").to_string();
    assert_eq!(token.len(), 32);
    assert!(server.url().ends_with(&format!("/?token={token}")));
    let host = format!("127.0.0.1:{}", server.addr().port());
    let (code, body) = get(&server, "/api/v1/status", &host, "");
    assert_eq!(code, 401);
    assert!(body.contains("token"), "{body}");
    assert_eq!(get(&server, "/api/v1/status", &host, "Authorization: Bearer wrong\r\n").0, 401);
    assert_eq!(get(&server, "/api/v1/status", &host, &format!("Authorization: Bearer {token}\r\n")).0, 200);
    assert_eq!(get(&server, &format!("/api/v1/status?token={token}"), &host, "").0, 200);
    // A second run has a token of its own.
    let (other, _) = self::live("lls");
    let second = Server::start_with("0.0.0.0:0", other, quick()).unwrap();
    assert_ne!(second.token(), Some(token.as_str()));
}

#[test]
fn oversized_slow_and_surplus_clients_are_refused_without_holding_up_others() {
    let (live, _) = live("lls");
    let server = Server::start_with("127.0.0.1:0", live, quick()).unwrap();
    let host = server.addr().to_string();
    let big = format!("GET /api/v1/status HTTP/1.1\r\nHost: {host}\r\nX-Pad: {}\r\n\r\n", "a".repeat(9000));
    assert_eq!(raw(&server, big.as_bytes()).0, 431);
    let body = "x".repeat(2000);
    let post = format!(
        "POST /api/v1/pause HTTP/1.1\r\nHost: {host}\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    assert_eq!(raw(&server, post.as_bytes()).0, 413);
    // Clients that connect and say nothing fill every place…
    let silent: Vec<TcpStream> =
        (0..lightrig_serve::MAX_CONNECTIONS).map(|_| TcpStream::connect(server.addr()).unwrap()).collect();
    let deadline = Instant::now() + Duration::from_secs(10);
    while server.connections() < lightrig_serve::MAX_CONNECTIONS {
        assert!(Instant::now() < deadline, "the silent clients were taken in");
        std::thread::yield_now();
    }
    // …so the next is told at once, not left waiting…
    let (code, body) = get(&server, "/api/v1/status", &host, "");
    assert_eq!(code, 503, "{body}");
    // …and once they are gone, requests are answered again.
    drop(silent);
    let deadline = Instant::now() + Duration::from_secs(10);
    while server.connections() > 0 {
        assert!(Instant::now() < deadline, "the silent clients' threads ended");
        std::thread::yield_now();
    }
    assert_eq!(get(&server, "/api/v1/status", &host, "").0, 200);
}

/// A WebSocket client of `server`'s feed from `since`.
fn ws(server: &Server, since: Option<u64>) -> tungstenite::WebSocket<TcpStream> {
    let s = TcpStream::connect(server.addr()).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let q = since.map(|n| format!("?since={n}")).unwrap_or_default();
    let url = format!("ws://{}/api/v1/ws{q}", server.addr());
    tungstenite::client::client(url.as_str(), s).unwrap().0
}

fn next_json(ws: &mut tungstenite::WebSocket<TcpStream>) -> serde_json::Value {
    loop {
        match ws.read().unwrap() {
            Message::Text(t) => return serde_json::from_str(&t).unwrap(),
            Message::Close(_) => panic!("closed"),
            _ => {}
        }
    }
}

/// The next message of `kind`, skipping others.
fn next_of(ws: &mut tungstenite::WebSocket<TcpStream>, kind: &str) -> serde_json::Value {
    loop {
        let m = next_json(ws);
        if m["type"] == kind {
            return m;
        }
    }
}

#[test]
fn the_websocket_feeds_records_frames_status_and_the_end() {
    let (live, _) = live("lls");
    let server = Server::start_with("127.0.0.1:0", live.clone(), quick()).unwrap();
    live.record(b"{\"type\":\"Early\"}");
    let mut w = ws(&server, Some(0));
    let hello = next_json(&mut w);
    assert_eq!((hello["type"].as_str(), hello["api"].as_u64()), (Some("hello"), Some(1)));
    assert_eq!(hello["status"]["journal"]["next"], 1);
    let r = next_of(&mut w, "record");
    assert_eq!((r["seq"].as_u64(), r["record"]["type"].as_str()), (Some(0), Some("Early")));
    live.record(b"{\"type\":\"Late\"}");
    let r = next_of(&mut w, "record");
    assert_eq!((r["seq"].as_u64(), r["record"]["type"].as_str()), (Some(1), Some("Late")));
    assert_eq!(live.watchers(), 1, "an open WebSocket watches");
    let dir = scratch("ws");
    live.arrived(&[captured(2, 0, png_frame(&dir, 8, 4, |x, _| x as f32 / 7.0))]);
    let f = next_of(&mut w, "frame");
    assert_eq!(
        (f["camera"].as_u64(), f["width"].as_u64(), f["clipped"].as_u64()),
        (Some(2), Some(8), Some(4))
    );
    live.ended(Ok(()));
    let s = next_of(&mut w, "status");
    assert_eq!(s["state"], "finished");
    let end = next_of(&mut w, "end");
    assert_eq!(end["state"], "finished");
    drop(w);
    let deadline = Instant::now() + Duration::from_secs(10);
    while live.watchers() > 0 {
        assert!(Instant::now() < deadline, "the WebSocket's watch ended with it");
        std::thread::yield_now();
    }
}

#[test]
fn a_websocket_client_behind_the_records_kept_is_told_it_lagged() {
    let (live, _) = live("lls");
    let server = Server::start_with("127.0.0.1:0", live.clone(), quick()).unwrap();
    let n = lightrig_host::live::RECORDS_KEPT as u64 + 100;
    for i in 0..n {
        live.record(format!("{{\"n\":{i}}}").as_bytes());
    }
    let mut w = ws(&server, Some(0));
    next_of(&mut w, "hello");
    let lag = next_json(&mut w);
    assert_eq!(lag, serde_json::json!({"type": "lagged", "skipped": 100, "next": 100}));
    let r = next_of(&mut w, "record");
    assert_eq!((r["seq"].as_u64(), r["record"]["n"].as_u64()), (Some(100), Some(100)));
}

#[test]
fn a_websocket_client_that_never_reads_is_dropped_and_holds_up_nothing() {
    let (live, _) = live("lls");
    let server = Server::start_with("127.0.0.1:0", live.clone(), quick()).unwrap();
    // Connected, and then never read from again.
    let idle = ws(&server, None);
    let deadline = Instant::now() + Duration::from_secs(10);
    while live.watchers() == 0 {
        assert!(Instant::now() < deadline, "the WebSocket was taken in");
        std::thread::yield_now();
    }
    // Far more than the socket buffers hold: the server's writes block, then time out.
    let pad = "p".repeat(16 * 1024);
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut written = 0u64;
    while live.watchers() > 0 {
        assert!(Instant::now() < deadline, "a client that never reads is dropped at the write timeout");
        // The run's side: every record goes in at once, whatever the client does.
        for _ in 0..64 {
            live.record(format!("{{\"pad\":\"{pad}\",\"n\":{written}}}").as_bytes());
            written += 1;
        }
        // Others are still answered meanwhile.
        assert_eq!(endpoint(&server).get_json("/api/v1/status").unwrap().0, 200);
    }
    assert_eq!(live.watchers(), 0, "the dropped client no longer counts as watching");
    assert!(written > 64, "records went in while the client stalled: {written}");
    drop(idle);
}
