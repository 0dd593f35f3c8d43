//! `lightrig devices`, `lightrig info`, `lightrig stop` and `lightrig schema`: what is attached,
//! what a device says about itself, an emergency stop from anywhere, and what this build
//! speaks.

use std::process::ExitCode;

use lightrig_host::client::{fresh_nonce, Client};
use lightrig_host::transport::{candidates, Connect, Transport};
use lightrig_protocol::session::Capabilities;
use lightrig_protocol::{Command, Reply, MAX_FRAME, MAX_PACKET, PROTOCOL_VERSION, SCHEMA_HASH};

use crate::error::{DEVICE, USAGE};

/// Arguments of `lightrig devices`.
#[derive(Debug, clap::Args)]
pub struct DevicesArgs {
    /// Say Hello to every port (a port that is not a lightrig controller costs a 3 s timeout).
    #[arg(long)]
    pub probe: bool,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
    /// Also open the GenICam camera at this address (repeatable): discovery by broadcast
    /// finds no camera on loopback or on another subnet.
    #[arg(long = "genicam", value_name = "ADDRESS")]
    pub genicam: Vec<String>,
}

/// Arguments of `lightrig info`.
#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// `virtual`, `serial:PATH[@BAUD]`, `usb` or `usb:SERIAL`.
    #[arg(long, default_value = "virtual")]
    pub connect: Connect,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

fn connect(spec: &Connect) -> Result<Client<Box<dyn Transport>>, (u8, String)> {
    let transport = lightrig_sim::transport::open(spec).map_err(|e| (DEVICE, e.to_string()))?;
    Client::connect(transport, fresh_nonce()).map_err(|e| (DEVICE, e.to_string()))
}

/// The firmware images the device holds (running, fallback) and where an update stands;
/// `null` where the board has no bootloader to update it over the link.
fn update_json(c: &mut Client<Box<dyn Transport>>) -> serde_json::Value {
    use lightrig_protocol::update::UpdateCommand;
    let Ok(st) = lightrig_host::flash::update(c, UpdateCommand::Status) else {
        return serde_json::Value::Null;
    };
    if st.slot == 0 {
        return serde_json::Value::Null;
    }
    let image = |i: Option<lightrig_protocol::update::ImageInfo>| {
        i.map(|i| format!("{}.{}.{}", i.version.major, i.version.minor, i.version.patch))
    };
    serde_json::json!({
        "running": image(st.running),
        "fallback": image(st.fallback),
        "phase": format!("{:?}", st.phase),
        "slot_bytes": st.slot,
    })
}

fn info_json(c: &mut Client<Box<dyn Transport>>) -> serde_json::Value {
    let update = update_json(c);
    // The device's link counters since it started (§5.3): frames, rejections, retransmissions,
    // the datagrams it dropped.
    let link = match c.request(Command::GetStatus) {
        Ok(Reply::Status(s)) => serde_json::to_value(s.link).unwrap_or_default(),
        _ => serde_json::Value::Null,
    };
    let i = c.info();
    serde_json::json!({
        "update": update,
        "link": link,
        "device": c.transport().describe(),
        "board": format!("{:?}", i.board),
        "firmware": format!("{}.{}.{}", i.firmware.major, i.firmware.minor, i.firmware.patch),
        "protocol_version": i.protocol_version,
        "schema_hash": format!("0x{:016x}", i.schema_hash),
        "serial": i.serial,
        "tick_hz": i.tick_hz,
        "reset_cause": format!("{:?}", i.reset_cause),
        "boot_id": i.boot_id,
        "capabilities": {
            "galvos": i.capabilities.galvos,
            "lasers": i.capabilities.lasers,
            "steppers": i.capabilities.steppers,
            "filter_wheels": i.capabilities.filter_wheels,
            "voice_coils": i.capabilities.voice_coils,
            "partials_per_coil": i.capabilities.partials_per_coil,
            "cameras": i.capabilities.cameras,
            "sequence_buffer": i.capabilities.sequence_buffer,
            "event_queue": i.capabilities.event_queue,
            "link_window": i.capabilities.link_window,
            "max_packet": i.capabilities.max_packet,
        },
        "clock": {
            "rate_ppm": c.clock().rate().map(|r| (r * 1e6 / f64::from(i.tick_hz) - 1.0) * 1e6),
            "residual_ticks": c.clock().residual(),
            "min_rtt_us": c.clock().min_rtt_us(),
        },
    })
}

/// `lightrig devices [--probe] [--json]`.
pub fn devices(args: &DevicesArgs) -> ExitCode {
    let mut rows = Vec::new();
    for c in candidates() {
        let answer = if args.probe {
            match c.connect.parse::<Connect>().map_err(|e| (USAGE, e)).and_then(|s| connect(&s)) {
                Ok(mut client) => Some(info_json(&mut client)),
                Err((_, e)) => Some(serde_json::json!({ "error": e })),
            }
        } else {
            None
        };
        rows.push(serde_json::json!({ "connect": c.connect, "description": c.description, "hello": answer }));
    }
    // GenICam cameras beside the controllers: a rig file names one by address or id.
    let cameras = match lightrig_genicam::cameras(&args.genicam) {
        Ok(cams) => cams
            .into_iter()
            .map(|c| {
                let address = if c.address.is_empty() { c.id.clone() } else { c.address.clone() };
                serde_json::json!({
                    "genicam": address,
                    "description": format!("{} {} ({}), id {}", c.vendor, c.model, c.protocol, c.id),
                })
            })
            .collect(),
        Err(e) if !args.genicam.is_empty() => {
            eprintln!("error: --genicam: {e}");
            return ExitCode::from(if lightrig_genicam::available() { DEVICE } else { USAGE });
        }
        Err(_) => Vec::new(),
    };
    rows.extend(cameras);
    if args.json {
        println!("{}", serde_json::Value::Array(rows));
    } else if rows.is_empty() {
        println!(
            "no serial ports, USB controllers or GenICam cameras found (the virtual rig is always there: \
             --connect virtual)"
        );
    } else {
        for r in &rows {
            let name = match r["genicam"].as_str() {
                Some(a) => format!("genicam:{a}"),
                None => r["connect"].as_str().unwrap_or("").to_string(),
            };
            println!("{:<28} {}", name, r["description"].as_str().unwrap_or(""));
            if !r["hello"].is_null() {
                println!("    {}", r["hello"]);
            }
        }
    }
    ExitCode::SUCCESS
}

/// `lightrig info [--connect SPEC] [--json]`.
pub fn info(args: &InfoArgs) -> ExitCode {
    match connect(&args.connect) {
        Ok(mut client) => {
            let v = info_json(&mut client);
            if args.json {
                println!("{v}");
            } else if let Some(map) = v.as_object() {
                for (k, val) in map {
                    match k.as_str() {
                        "capabilities" => {
                            println!("{k:<16} {}", capabilities_in_words(&client.info().capabilities))
                        }
                        "update" if val.is_null() => {
                            println!(
                                "{k:<16} not over the link (no bootloader: flash through the debug probe)"
                            )
                        }
                        "link" => println!("{k:<16} {}", link_in_words(val)),
                        "update" => println!(
                            "{k:<16} running {}, fallback {}, {}, slot {} bytes",
                            val["running"].as_str().unwrap_or("unknown"),
                            val["fallback"].as_str().unwrap_or("none"),
                            val["phase"].as_str().unwrap_or(""),
                            val["slot_bytes"]
                        ),
                        _ => println!("{k:<16} {val}"),
                    }
                }
            }
            ExitCode::SUCCESS
        }
        Err((code, e)) => {
            eprintln!("error: {e}");
            ExitCode::from(code)
        }
    }
}

/// The device's link counters (`info_json`'s `link`), in words.
fn link_in_words(val: &serde_json::Value) -> String {
    match serde_json::from_value::<lightrig_protocol::link::LinkStats>(val.clone()) {
        Ok(s) => format!(
            "since the device started: frames sent {}, received {}, rejected {}, resent {}; epochs started {}; \
             datagrams dropped {}",
            s.frames_sent,
            s.frames_received,
            s.rejected(),
            s.retransmits,
            s.syncs,
            s.datagrams_dropped
        ),
        Err(_) => "not read (the device did not answer GetStatus)".into(),
    }
}

/// What a device offers, in words.
pub fn capabilities_in_words(c: &Capabilities) -> String {
    let n = |count: u8, one: &str, many: &str| format!("{count} {}", if count == 1 { one } else { many });
    format!(
        "{}, {}, {}, {}, {} ({} partials each), {}; sequence buffer {} items, event queue {}, link window {}, \
         packets up to {} B",
        n(c.galvos, "galvo pair", "galvo pairs"),
        n(c.lasers, "laser", "lasers"),
        n(c.steppers, "stepper", "steppers"),
        n(c.filter_wheels, "filter wheel", "filter wheels"),
        n(c.voice_coils, "voice coil", "voice coils"),
        c.partials_per_coil,
        n(c.cameras, "camera trigger", "camera triggers"),
        c.sequence_buffer,
        c.event_queue,
        c.link_window,
        c.max_packet
    )
}

/// Arguments of `lightrig stop`.
#[derive(Debug, clap::Args)]
pub struct StopArgs {
    /// The device: `serial:PATH[@BAUD]`, `usb` or `usb:SERIAL`. Without it, every running
    /// `lightrig acquire`/`resume` of this user is stopped.
    #[arg(long, conflicts_with = "url")]
    pub connect: Option<Connect>,
    /// A run's live endpoint (`acquire --serve`), as it printed it: `http://HOST:PORT/`, from
    /// this machine or another (docs/live-api.md).
    #[arg(long)]
    pub url: Option<String>,
    /// The endpoint's token, if it was not given in `--url` (an endpoint off loopback).
    #[arg(long, requires = "url")]
    pub token: Option<String>,
}

/// `lightrig stop --url URL`: the stop through a run's live endpoint; success once the device
/// answered it.
fn stop_through_endpoint(url: &str, token: Option<&str>) -> ExitCode {
    let reply = lightrig_serve::client::Endpoint::parse(url, token).and_then(|e| e.post_json("/api/v1/stop"));
    match reply {
        Ok((200, v)) if v["stop"]["answered"] == true => {
            println!("{url}: {} (the run sent it; it now ends)", v["message"].as_str().unwrap_or("stopped"));
            ExitCode::SUCCESS
        }
        Ok((200, v)) => {
            eprintln!("error: {url}: {}", v["message"].as_str().unwrap_or("the stop was not confirmed"));
            ExitCode::from(DEVICE)
        }
        Ok((code, v)) => {
            eprintln!("error: {url}: {code}: {}", v["error"].as_str().unwrap_or("refused"));
            ExitCode::from(if code == 401 || code == 403 { USAGE } else { DEVICE })
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(DEVICE)
        }
    }
}

/// `lightrig stop [--connect SPEC | --url URL]`: an emergency stop from another terminal. The device turns
/// its lasers off, stops its motors without deceleration, parks its galvos and latches the
/// fault until a person clears it (`lightrig resume` asks). A device that a running
/// `lightrig acquire` or `resume` holds is reached through that run's control socket (the
/// port is the run's alone); any other directly.
pub fn stop(args: &StopArgs) -> ExitCode {
    if let Some(url) = &args.url {
        return stop_through_endpoint(url, args.token.as_deref());
    }
    let Some(spec) = &args.connect else { return stop_every_run() };
    #[cfg(unix)]
    for key in super::acquire::control_keys(spec) {
        match lightrig_host::control::ask(&lightrig_host::control::socket_for(&key), "stop") {
            Ok(Some(reply)) => return said_by_run(&reply),
            Ok(None) => {}
            Err(e) => eprintln!("warning: the control socket of {key}: {e}; trying the port itself"),
        }
    }
    let mut client = match connect(spec) {
        Ok(c) => c,
        Err((code, e)) => {
            eprintln!("error: {e}");
            return ExitCode::from(code);
        }
    };
    if let Err(e) = client.emergency_stop() {
        eprintln!("error: {e}");
        return ExitCode::from(DEVICE);
    }
    let state = match client.request(Command::GetStatus) {
        Ok(Reply::Status(s)) => {
            format!("{:?}; lasers armed {:#010b}, on {:#010b}", s.state, s.armed, s.lasers_on)
        }
        _ => "state not read".into(),
    };
    println!(
        "{}: emergency stop sent and answered ({state}); the stop stays latched until a person clears it: \
         `lightrig resume` at a terminal asks (or --clear-stop)",
        client.transport().describe()
    );
    ExitCode::SUCCESS
}

/// A run's answer to `stop`: printed; success only if the device answered the stop.
#[cfg(unix)]
fn said_by_run(reply: &str) -> ExitCode {
    if let Some(rest) = reply.strip_prefix("stopped: ") {
        println!("{rest} (the run that holds the port sent it; it now ends)");
        ExitCode::SUCCESS
    } else {
        eprintln!("error: {}", reply.trim_start_matches("unconfirmed: ").trim_start_matches("error: "));
        ExitCode::from(DEVICE)
    }
}

/// `lightrig stop` with no device named: every run serving a control socket.
fn stop_every_run() -> ExitCode {
    #[cfg(unix)]
    {
        let runs = lightrig_host::control::running();
        if runs.is_empty() {
            eprintln!(
                "error: no running `lightrig acquire` or `resume` of this user was found (in {}); name the \
                 device with --connect serial:PATH to stop it directly",
                lightrig_host::control::socket_dir().display()
            );
            return ExitCode::from(USAGE);
        }
        let mut code = ExitCode::SUCCESS;
        for (socket, _) in runs {
            match lightrig_host::control::ask(&socket, "stop") {
                Ok(Some(reply)) => {
                    if said_by_run(&reply) != ExitCode::SUCCESS {
                        code = ExitCode::from(DEVICE);
                    }
                }
                Ok(None) => {}
                Err(e) => {
                    eprintln!("error: {}: {e}", socket.display());
                    code = ExitCode::from(DEVICE);
                }
            }
        }
        code
    }
    #[cfg(not(unix))]
    {
        eprintln!("error: name the device with --connect");
        ExitCode::from(USAGE)
    }
}

/// `lightrig schema`.
pub fn schema() -> ExitCode {
    println!("protocol version {PROTOCOL_VERSION}");
    println!("schema hash      0x{SCHEMA_HASH:016x}");
    println!("max packet       {MAX_PACKET} bytes, max frame {MAX_FRAME} bytes");
    ExitCode::SUCCESS
}
