//! `lightrig acquire` and `lightrig resume`: a rig file's plan, run into a session directory.

use std::path::{Path, PathBuf};

use lightrig_protocol::config::HomingMode;
use lightrig_protocol::event::Event;
use lightrig_protocol::sequence::AxisRef;
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::Command;

use crate::acquire::{self, plan_summary, Captured, DirectoryInput, FrameInput, Progress, StepPreparation};
use crate::client::Client;
use crate::plan::{from_rig, Plan};
use crate::rigfile::{self, FrameSource, RigFile};
use crate::session::{Manifest, PlanStep, Session};
use crate::transport::{Connect, Transport};
use crate::virtual_rig::camera::VirtualCamera;
use crate::virtual_rig::timeline::Timeline;

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

/// Opens the link `spec` names. The virtual device is wired as the rig file says (switch
/// polarities, interlocks) and comes with its timeline, for a virtual camera to follow.
fn open(rig: &RigFile, spec: &Connect) -> Result<(Box<dyn Transport>, Option<Timeline>), CliError> {
    Ok(match spec {
        Connect::Virtual => {
            let info = crate::selfcheck::virtual_device_info();
            let (t, timeline) = crate::virtual_rig::connect_for_camera(rig, info, false);
            (Box::new(t), Some(timeline))
        }
        _ => (spec.open().map_err(|e| err(DEVICE, e.to_string()))?, None),
    })
}

/// Connects, uploads the rig's configuration and homes what has a homing procedure.
pub fn bring_up(rig: &RigFile, spec: &Connect) -> Result<Client<Box<dyn Transport>>, CliError> {
    bring_up_on(rig, open(rig, spec)?.0)
}

/// [`bring_up`] on a transport already open.
pub fn bring_up_on(
    rig: &RigFile,
    transport: Box<dyn Transport>,
) -> Result<Client<Box<dyn Transport>>, CliError> {
    let nonce = std::process::id() ^ (std::time::SystemTime::now().elapsed().map_or(7, |d| d.subsec_nanos()));
    let mut client = Client::connect(transport, nonce).map_err(|e| err(DEVICE, e.to_string()))?;
    // A device an earlier run left mid-sequence or faulted takes no configuration until then.
    acquire::recover(&mut client).map_err(|e| err(DEVICE, e.to_string()))?;
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
    let deadline_us = homing_timeout_us(rig);
    let give_up = client.transport().now_us().saturating_add(deadline_us);
    while !homing.is_empty() {
        let left = give_up.saturating_sub(client.transport().now_us());
        let e = client.next_event(left).map_err(|e| err(DEVICE, e.to_string()))?;
        match e.map(|e| e.event) {
            Some(Event::Homed { axis, .. }) => homing.retain(|a| *a != axis),
            Some(Event::Fault { cause, .. }) => {
                return Err(err(
                    DEVICE,
                    format!("homing failed: {cause:?}; check the switches and their wiring"),
                ))
            }
            Some(_) => {}
            None => {
                return Err(err(
                    DEVICE,
                    format!(
                        "homing did not finish within {:.0} s (1.5 × the longest seek at the rig file's \
                         homing speed, + 10 s): {homing:?}; check the switches and the homing speed",
                        deadline_us as f64 / 1e6
                    ),
                ))
            }
        }
    }
    Ok(client)
}

/// How long homing may take, µs: 1.5 × the longest seek (a linear axis' whole travel between
/// its limits, else 1 m, plus twice its back-off; two turns of a rotary axis or a filter wheel)
/// at the axis' homing speed, + 10 s. The axes home together.
pub fn homing_timeout_us(rig: &RigFile) -> u64 {
    let seek_s = |s: &crate::rigfile::Stepper| -> f64 {
        if s.homing.mode == HomingMode::None || s.homing.speed <= 0.0 {
            return 0.0;
        }
        let travel = match s.kind {
            lightrig_protocol::config::AxisKind::Rotary => 720.0,
            lightrig_protocol::config::AxisKind::Linear => s.limits.map_or(1000.0, |(lo, hi)| hi - lo),
        };
        (travel + 2.0 * s.homing.backoff.abs()) / s.homing.speed
    };
    // A wheel's max_speed is in rev/s.
    let wheels = rig.filter_wheels.iter().map(|w| 2.0 / w.max_speed.max(1e-3));
    let longest = rig.steppers.iter().map(seek_s).chain(wheels).fold(0.0, f64::max);
    ((1.5 * longest + 10.0) * 1e6).min(u64::MAX as f64 / 2.0) as u64
}

/// Where a virtual camera writes its files inside a session directory (scratch: the session
/// stores its own copy of each frame; removed when the session completes).
pub const VIRTUAL_CAMERA_DIR: &str = "virtual-camera";

/// The frame inputs of the rig's cameras, as one. A virtual camera renders
/// [`crate::virtual_rig::scene_for`] the rig into `session/virtual-camera/camN/`, following the
/// virtual device's `timeline` if it runs on one (else from each trigger's snapshot: a real
/// controller with no camera attached).
fn frame_input(
    rig: &RigFile,
    session: &Path,
    timeline: Option<Timeline>,
    tick_hz: u32,
) -> Result<Box<dyn FrameInput>, CliError> {
    if rig.cameras.is_empty() {
        return Err(err(INPUT, format!("{}: the rig has no [[camera]]", rig.path.display())));
    }
    let scratch = session.join(VIRTUAL_CAMERA_DIR);
    // Files of an earlier run would hide this run's files of the same numbers.
    if scratch.exists() {
        std::fs::remove_dir_all(&scratch).map_err(|e| err(FAILURE, format!("{}: {e}", scratch.display())))?;
    }
    let mut inputs: Vec<Box<dyn FrameInput>> = Vec::new();
    for cam in &rig.cameras {
        inputs.push(match &cam.source {
            FrameSource::Directory { dir, pattern } => {
                Box::new(DirectoryInput::new(cam.camera, dir, pattern).map_err(|e| err(INPUT, e))?)
            }
            FrameSource::Virtual => {
                let dir = scratch.join(format!("cam{}", cam.camera));
                let (scene, sensor) = crate::virtual_rig::scene_for(rig, 1 + u64::from(cam.camera));
                let mut camera = VirtualCamera::new(rig, cam.camera, scene, sensor, tick_hz, &dir)
                    .map_err(|e| err(FAILURE, format!("{}: {e}", dir.display())))?;
                match &timeline {
                    // The in-process device's time waits for the camera: render in step.
                    Some(t) => {
                        camera.follow(t.clone());
                        Box::new(camera)
                    }
                    // A controller in real time must not wait on the rendering.
                    None => Box::new(acquire::Background::new(Box::new(camera))),
                }
            }
        });
    }
    Ok(Box::new(acquire::Cameras(inputs)))
}

/// Checks the directory sources before connecting, so a wrong path fails at once.
fn check_sources(rig: &RigFile) -> Result<(), CliError> {
    if rig.cameras.is_empty() {
        return Err(err(INPUT, format!("{}: the rig has no [[camera]]", rig.path.display())));
    }
    for cam in &rig.cameras {
        if let FrameSource::Directory { dir, pattern } = &cam.source {
            DirectoryInput::new(cam.camera, dir, pattern).map_err(|e| err(INPUT, e))?;
        }
    }
    Ok(())
}

/// How `acquire` and `resume` meet what a step asks of the host ([`acquire::step_requests`]):
/// on the virtual rig its instruments do it; else a person is asked at the terminal, or with
/// `--yes` it is taken as done (a scripted run on a rig set up beforehand).
pub struct OperatorPrompt {
    /// The device is the virtual rig.
    pub virtual_rig: bool,
    /// `--yes`.
    pub assume_done: bool,
}

impl StepPreparation for OperatorPrompt {
    fn prepare(&mut self, step: &crate::plan::Step, requests: &[String]) -> Result<String, String> {
        use std::io::{BufRead, IsTerminal};
        let list = requests.join("; ");
        if self.virtual_rig {
            eprintln!("\nstep {} ({}): the virtual rig does: {list}", step.id, step.name);
            return Ok("virtual".into());
        }
        eprintln!("\nstep {} ({}) needs:", step.id, step.name);
        for r in requests {
            eprintln!("  - {r}");
        }
        if self.assume_done {
            eprintln!("  (--yes: taken as done)");
            return Ok("assumed".into());
        }
        let stdin = std::io::stdin();
        if !stdin.is_terminal() {
            return Err(format!(
                "step {} ({}) needs a person: {list}. Run `lightrig resume` in a terminal to be asked, \
                 or pass --yes if the rig is already set up that way",
                step.id, step.name
            ));
        }
        eprint!("press Enter when done (q, Enter: stop here): ");
        let mut line = String::new();
        stdin.lock().read_line(&mut line).map_err(|e| format!("reading the answer: {e}"))?;
        if line.trim().eq_ignore_ascii_case("q") {
            return Err(format!("stopped by the operator before step {} ({})", step.id, step.name));
        }
        Ok("operator".into())
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

/// How many times `acquire` and `resume` try to get a lost device back, waiting 1, 2, 4, 8,
/// then 10 s before each: about 1.5 minutes to plug the cable back in.
pub const RECONNECT_ATTEMPTS: u32 = 12;

/// The wait before reconnection attempt `k` (1, 2, …), ms.
pub fn reconnect_backoff_ms(k: u32) -> u64 {
    1000u64.saturating_mul(1 << k.saturating_sub(1).min(4)).min(10_000)
}

fn run(
    client: Client<Box<dyn Transport>>,
    rig: &RigFile,
    spec: &Connect,
    session: &mut Session,
    plan: &Plan,
    input: &mut dyn FrameInput,
    prep: &mut OperatorPrompt,
) -> Result<(), CliError> {
    let start = std::time::Instant::now();
    // A real device that goes away (unplug, port reset) is waited for and brought up again;
    // the virtual one lives in this process and cannot.
    let attempts = if *spec == Connect::Virtual { 0 } else { RECONNECT_ATTEMPTS };
    let mut reconnect = |old: Option<Box<dyn Transport>>, k: u32| {
        drop(old); // close the old port before opening it again
        std::thread::sleep(std::time::Duration::from_millis(reconnect_backoff_ms(k)));
        let (t, _) = open(rig, spec).map_err(|e| client_error(spec, e))?;
        bring_up_on(rig, t).map_err(|e| client_error(spec, e))
    };
    let r = acquire::run_reconnecting(
        client,
        &mut reconnect,
        attempts,
        session,
        plan,
        &mut Boxed(input),
        prep,
        progress_printer(start),
        |m| eprintln!("\n{m}"),
    );
    eprintln!();
    r.map_err(|e| match e {
        acquire::AcquireError::Preparation(_) => err(FAILURE, e.to_string()),
        _ => err(DEVICE, e.to_string()),
    })?;
    let scratch = session.dir().join(VIRTUAL_CAMERA_DIR);
    if scratch.exists() {
        std::fs::remove_dir_all(&scratch).map_err(|e| err(FAILURE, format!("{}: {e}", scratch.display())))?;
    }
    eprintln!("session complete: {}", session.dir().display());
    Ok(())
}

/// A bring-up failure during reconnection, as the client error the engine reports.
fn client_error(spec: &Connect, e: CliError) -> crate::client::ClientError {
    crate::client::ClientError::Io { device: spec.to_string(), error: std::io::Error::other(e.message) }
}

/// `lightrig acquire RIG --session DIR [--yes]`.
pub fn acquire(
    rig_path: &Path,
    dir: &Path,
    over: Option<&Connect>,
    assume_done: bool,
) -> Result<(), CliError> {
    let rig = RigFile::load(rig_path).map_err(|e| err(INPUT, e.to_string()))?;
    let text =
        std::fs::read_to_string(rig_path).map_err(|e| err(INPUT, format!("{}: {e}", rig_path.display())))?;
    if dir.join("manifest.json").exists() {
        return Err(err(
            INPUT,
            format!("{} already holds a session; continue it with `lightrig resume {0}`", dir.display()),
        ));
    }
    check_sources(&rig)?;
    let spec = connect_spec(&rig, over);
    let (transport, timeline) = open(&rig, &spec)?;
    let client = bring_up_on(&rig, transport)?;
    let plan = from_rig::plan(&rig, client.info()).map_err(|e| err(INPUT, e.to_string()))?;
    print_summary(&plan, client.info());
    let manifest = Manifest::new(text, client.info(), plan_summary(&plan));
    let mut session = Session::create(dir, manifest).map_err(|e| err(INPUT, e.to_string()))?;
    let mut input = frame_input(&rig, dir, timeline, client.info().tick_hz)?;
    let mut prep = OperatorPrompt { virtual_rig: spec == Connect::Virtual, assume_done };
    run(client, &rig, &spec, &mut session, &plan, input.as_mut(), &mut prep)
}

/// `lightrig resume DIR [--rig RIG] [--yes]`: the session's own rig file (the copy in its
/// manifest; `rig` says where the original lives, for its relative paths, and must be
/// unchanged), planned again and checked against the manifest, then the steps not yet done.
pub fn resume(
    dir: &Path,
    rig_path: Option<&Path>,
    over: Option<&Connect>,
    assume_done: bool,
) -> Result<(), CliError> {
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
    check_sources(&rig)?;
    let spec = connect_spec(&rig, over);
    let (transport, timeline) = open(&rig, &spec)?;
    let client = bring_up_on(&rig, transport)?;
    let plan = from_rig::plan(&rig, client.info()).map_err(|e| err(INPUT, e.to_string()))?;
    if !same_steps(&plan_summary(&plan).steps, &session.manifest().plan.steps) {
        return Err(err(
            INPUT,
            "the rig file's plan no longer matches the session's (a different device tick rate or a changed \
             planner); finish it with the host version that started it",
        ));
    }
    print_summary(&plan, client.info());
    let mut input = frame_input(&rig, dir, timeline, client.info().tick_hz)?;
    let mut prep = OperatorPrompt { virtual_rig: spec == Connect::Virtual, assume_done };
    run(client, &rig, &spec, &mut session, &plan, input.as_mut(), &mut prep)
}

/// Whether a re-made plan is the one a session started with: the same steps (ids, names,
/// triggers per camera, `meta`). Sessions written before plans were lazy also kept each shot's
/// label (`extra.shots`); those are not compared.
fn same_steps(now: &[PlanStep], then: &[PlanStep]) -> bool {
    now.len() == then.len()
        && now.iter().zip(then).all(|(a, b)| {
            (a.id, &a.name, &a.triggers, a.extra.get("meta"))
                == (b.id, &b.name, &b.triggers, b.extra.get("meta"))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example(name: &str) -> RigFile {
        RigFile::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs").join(name)).unwrap()
    }

    #[test]
    fn homing_may_take_one_and_a_half_seeks_plus_ten_seconds() {
        // Gantry: limits ±200 mm, back-off 2 mm, 20 mm/s: (400 + 4) / 20 = 20.2 s.
        assert_eq!(homing_timeout_us(&example("lls-gantry.toml")), 40_300_000);
        // Turntable seeking its index at 2 deg/s: two turns, 360 s.
        assert_eq!(homing_timeout_us(&example("fluorescent-immersion.toml")), 550_000_000);
    }

    #[test]
    fn reconnection_waits_double_up_to_ten_seconds() {
        let waits: Vec<u64> = (1..=7).map(reconnect_backoff_ms).collect();
        assert_eq!(waits, [1_000, 2_000, 4_000, 8_000, 10_000, 10_000, 10_000]);
        let total: u64 = (1..=RECONNECT_ATTEMPTS).map(reconnect_backoff_ms).sum();
        assert_eq!(total, 95_000);
    }
}
