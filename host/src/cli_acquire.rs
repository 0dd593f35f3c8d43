//! `lightrig acquire` and `lightrig resume`: a rig file's plan, run into a session directory.

use std::path::{Path, PathBuf};

use lightrig_protocol::config::HomingMode;
use lightrig_protocol::event::Event;
use lightrig_protocol::sequence::AxisRef;
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::Command;

use crate::acquire::{self, plan_summary, Captured, DirectoryInput, FrameInput, Progress};
use crate::client::Client;
use crate::plan::{from_rig, Plan};
use crate::rigfile::{self, FrameSource, RigFile};
use crate::session::{Manifest, Session};
use crate::transport::{Connect, Transport};

/// An error for the command line: message and exit code.
#[derive(Debug)]
pub struct CliError {
    /// Exit code.
    pub code: u8,
    /// What to print.
    pub message: String,
}

fn err(code: u8, message: impl Into<String>) -> CliError {
    CliError { code, message: message.into() }
}

/// Exit code: something failed at run time.
pub const FAILURE: u8 = 1;
/// Exit code: the device could not be reached, or refused.
pub const DEVICE: u8 = 3;
/// Exit code: the rig file or the session is wrong.
pub const INPUT: u8 = 4;

fn connect_spec(rig: &RigFile, over: Option<&Connect>) -> Connect {
    over.cloned().unwrap_or_else(|| match &rig.connect {
        rigfile::Connect::Virtual => Connect::Virtual,
        rigfile::Connect::Serial { port, baud } => Connect::Serial { path: port.clone(), baud: *baud },
        rigfile::Connect::Usb => Connect::Usb { serial: None },
    })
}

/// Connects, uploads the rig's configuration and homes what has a homing procedure.
pub fn bring_up(rig: &RigFile, spec: &Connect) -> Result<Client<Box<dyn Transport>>, CliError> {
    let transport: Box<dyn Transport> = match spec {
        // The virtual device is wired as the rig file says (switch polarities, interlocks).
        Connect::Virtual => {
            Box::new(crate::virtual_rig::connect(rig, crate::selfcheck::virtual_device_info()))
        }
        _ => spec.open().map_err(|e| err(DEVICE, e.to_string()))?,
    };
    bring_up_on(rig, transport)
}

/// [`bring_up`] on a transport already open.
pub fn bring_up_on(
    rig: &RigFile,
    transport: Box<dyn Transport>,
) -> Result<Client<Box<dyn Transport>>, CliError> {
    let nonce = std::process::id() ^ (std::time::SystemTime::now().elapsed().map_or(7, |d| d.subsec_nanos()));
    let mut client = Client::connect(transport, nonce).map_err(|e| err(DEVICE, e.to_string()))?;
    if let Some(s) = &rig.safety {
        client.set_heartbeat_us((s.heartbeat_timeout_ms * 1000.0 / 4.0) as u64);
    }
    let items = rig.config_items(client.info()).map_err(|e| err(INPUT, e.to_string()))?;
    for item in items {
        client.request(Command::Configure(item)).map_err(|e| err(DEVICE, e.to_string()))?;
    }
    let mut homing: Vec<AxisRef> = rig
        .steppers
        .iter()
        .filter(|s| s.homing.mode != HomingMode::None)
        .map(|s| AxisRef::Stepper(s.axis))
        .chain(rig.filter_wheels.iter().map(|w| AxisRef::FilterWheel(w.wheel)))
        .collect();
    for &a in &homing {
        client.request(Command::Home(a)).map_err(|e| err(DEVICE, e.to_string()))?;
    }
    while !homing.is_empty() {
        let e = client.next_event(120_000_000).map_err(|e| err(DEVICE, e.to_string()))?;
        match e.map(|e| e.event) {
            Some(Event::Homed { axis, .. }) => homing.retain(|a| *a != axis),
            Some(Event::Fault { cause, .. }) => {
                return Err(err(
                    DEVICE,
                    format!("homing failed: {cause:?}; check the switches and their wiring"),
                ))
            }
            Some(_) => {}
            None => return Err(err(DEVICE, format!("homing did not finish within 120 s: {homing:?}"))),
        }
    }
    Ok(client)
}

/// The frame inputs of the rig's cameras (one camera for now: the planners use camera 0).
fn frame_input(rig: &RigFile) -> Result<Box<dyn FrameInput>, CliError> {
    let cam = rig
        .cameras
        .first()
        .ok_or_else(|| err(INPUT, format!("{}: the rig has no [[camera]]", rig.path.display())))?;
    match &cam.source {
        FrameSource::Directory { dir, pattern } => Ok(Box::new(
            DirectoryInput::new(cam.camera, dir, pattern).map_err(|e| err(INPUT, e))?,
        )),
        FrameSource::Virtual => Err(err(
            INPUT,
            format!(
                "{}: camera {} uses the virtual camera, which this build cannot render yet; give it a \
                 `source = {{ kind = \"directory\", path = …, pattern = … }}` where the camera software writes",
                rig.path.display(),
                cam.camera
            ),
        )),
    }
}

struct Boxed<'a>(&'a mut dyn FrameInput);

impl FrameInput for Boxed<'_> {
    fn begin_step(&mut self, step: &crate::plan::Step) -> std::io::Result<()> {
        self.0.begin_step(step)
    }
    fn on_trigger(
        &mut self,
        t: &lightrig_protocol::event::TriggerEvent,
        h: Option<f64>,
    ) -> std::io::Result<()> {
        self.0.on_trigger(t, h)
    }
    fn poll(&mut self, now: f64) -> std::io::Result<Vec<Captured>> {
        self.0.poll(now)
    }
}

fn print_summary(plan: &Plan, info: &DeviceInfo) {
    let s = plan.summary();
    eprintln!(
        "plan: {} ({} steps, {} frames, at least {:.0} s, {:.1} GB) on {:?} at {} Hz",
        plan.method,
        s.steps,
        s.triggers,
        s.min_duration_us as f64 / 1e6,
        s.bytes as f64 / 1e9,
        info.board,
        info.tick_hz
    );
}

fn progress_printer(start: std::time::Instant) -> impl FnMut(Progress) {
    move |p: Progress| {
        let elapsed = start.elapsed().as_secs_f64().max(1e-3);
        let done = p.steps_done.max(1) as f64;
        let eta = elapsed / done * (p.steps - p.steps_done) as f64;
        let bar = (20 * p.steps_done / p.steps.max(1)).min(20);
        eprint!(
            "\r[{}{}] step {}/{}  {} frames  {:.1} frames/s  ETA {:.0} s   ",
            "=".repeat(bar),
            " ".repeat(20 - bar),
            p.steps_done,
            p.steps,
            p.frames,
            p.frames as f64 / elapsed,
            eta
        );
    }
}

fn run(
    client: &mut Client<Box<dyn Transport>>,
    session: &mut Session,
    plan: &Plan,
    input: &mut dyn FrameInput,
) -> Result<(), CliError> {
    let start = std::time::Instant::now();
    let r = acquire::run(client, session, plan, &mut Boxed(input), progress_printer(start));
    eprintln!();
    r.map_err(|e| err(DEVICE, e.to_string()))?;
    eprintln!("session complete: {}", session.dir().display());
    Ok(())
}

/// `lightrig acquire RIG --session DIR`.
pub fn acquire(rig_path: &Path, dir: &Path, over: Option<&Connect>) -> Result<(), CliError> {
    let rig = RigFile::load(rig_path).map_err(|e| err(INPUT, e.to_string()))?;
    let text =
        std::fs::read_to_string(rig_path).map_err(|e| err(INPUT, format!("{}: {e}", rig_path.display())))?;
    if dir.join("manifest.json").exists() {
        return Err(err(
            INPUT,
            format!("{} already holds a session; continue it with `lightrig resume {0}`", dir.display()),
        ));
    }
    let mut input = frame_input(&rig)?;
    let mut client = bring_up(&rig, &connect_spec(&rig, over))?;
    let plan = from_rig::plan(&rig, client.info()).map_err(|e| err(INPUT, e.to_string()))?;
    print_summary(&plan, client.info());
    let manifest = Manifest::new(text, client.info(), plan_summary(&plan));
    let mut session = Session::create(dir, manifest).map_err(|e| err(INPUT, e.to_string()))?;
    run(&mut client, &mut session, &plan, input.as_mut())
}

/// `lightrig resume DIR [--rig RIG]`: the session's own rig file (the copy in its manifest;
/// `rig` says where the original lives, for its relative paths, and must be unchanged),
/// planned again and checked against the manifest, then the steps not yet done.
pub fn resume(dir: &Path, rig_path: Option<&Path>, over: Option<&Connect>) -> Result<(), CliError> {
    let (mut session, recovery) = Session::open(dir).map_err(|e| err(INPUT, e.to_string()))?;
    eprintln!("resuming {}: {recovery:?}", dir.display());
    if session.is_done() {
        eprintln!("{}: the session is already complete", dir.display());
        return Ok(());
    }
    let text = session.manifest().rig.clone();
    let base: PathBuf = match rig_path {
        Some(p) => {
            let now = std::fs::read_to_string(p).map_err(|e| err(INPUT, format!("{}: {e}", p.display())))?;
            if now != text {
                return Err(err(
                    INPUT,
                    format!(
                        "{} changed since the session started; resume with the original rig file",
                        p.display()
                    ),
                ));
            }
            p.to_path_buf()
        }
        None => PathBuf::from("rig.toml"),
    };
    let rig = RigFile::parse(&text, &base).map_err(|e| err(INPUT, e.to_string()))?;
    let mut input = frame_input(&rig)?;
    let mut client = bring_up(&rig, &connect_spec(&rig, over))?;
    let plan = from_rig::plan(&rig, client.info()).map_err(|e| err(INPUT, e.to_string()))?;
    if plan_summary(&plan).steps != session.manifest().plan.steps {
        return Err(err(
            INPUT,
            "the rig file's plan no longer matches the session's (a different device tick rate or a changed \
             planner); finish it with the host version that started it",
        ));
    }
    print_summary(&plan, client.info());
    run(&mut client, &mut session, &plan, input.as_mut())
}
