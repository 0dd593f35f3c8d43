//! `lightrig acquire` and `lightrig resume`: a rig file's plan, run into a session directory.

use std::path::{Path, PathBuf};

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::acquire::{
    self, plan_summary, Captured, DirectoryInput, FrameInput, Progress, StepPreparation,
};
use std::sync::Arc;

use lightrig_host::bringup::{bring_up_with, reconnect_backoff_ms, BringUpHooks, RECONNECT_ATTEMPTS};
use lightrig_host::client::{describe_fault, Client, ClientError, Interrupt};
use lightrig_host::overrides::{self, Override};
use lightrig_host::plan::{from_rig, Plan, Step};
use lightrig_host::rigfile::{self, FrameSource, RigFile};
use lightrig_host::session::{Manifest, PlanStep, Session};
use lightrig_host::transport::{Connect, Transport};
use lightrig_protocol::event::{FaultCause, TriggerEvent};
use lightrig_protocol::session::DeviceInfo;
use lightrig_sim::camera::VirtualCamera;
use lightrig_sim::scenes::scene_for;
use lightrig_sim::timeline::Timeline;
use lightrig_sim::transport::connect_for_camera;

use crate::error::{err, CliError, DEVICE, FAILURE, INCOMPLETE, INPUT, INTERRUPTED};

/// Arguments of `lightrig acquire`.
#[derive(Debug, clap::Args)]
pub struct AcquireArgs {
    /// The rig file (see docs/rigs).
    pub rig: PathBuf,
    /// Session directory to create.
    #[arg(long)]
    pub session: PathBuf,
    /// Override the rig file's `[device] connect`.
    #[arg(long)]
    pub connect: Option<Connect>,
    /// Take what steps ask of a person or of host instruments (`meta.operator`,
    /// `meta.host`) as done, without asking: for scripts on a rig set up beforehand.
    #[arg(long)]
    pub yes: bool,
    /// Clear an emergency stop the device has latched (Ctrl-C, `lightrig stop`, its stop
    /// input) without asking: a person has seen to the rig. Without it the stop is cleared
    /// only when a person answers at the terminal (`--yes` does not clear it).
    #[arg(long)]
    pub clear_stop: bool,
    /// Change one of the rig file's values for this run, `KEY=VALUE` (repeatable):
    /// `--set plan.step_mm=4 --set camera[0].pulse_us=500`. The session keeps the text that
    /// ran; `resume --rig` needs the same overrides.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<Override>,
    /// Where the run's live page and API (docs/live-api.md) are served: by default on
    /// 127.0.0.1:7878 (another free port if that one is taken, printed at start); an address
    /// other than loopback needs the token printed at start.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = lightrig_serve::DEFAULT_ADDR)]
    pub serve: Option<String>,
    /// Serve no live page or API.
    #[arg(long, conflicts_with = "serve")]
    pub no_serve: bool,
}

/// Arguments of `lightrig resume`.
#[derive(Debug, clap::Args)]
pub struct ResumeArgs {
    /// Session directory.
    pub session: PathBuf,
    /// The original rig file (for its relative paths; must be unchanged).
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Override the rig file's `[device] connect`.
    #[arg(long)]
    pub connect: Option<Connect>,
    /// Take what steps ask of a person or of host instruments (`meta.operator`,
    /// `meta.host`) as done, without asking: for scripts on a rig set up beforehand.
    #[arg(long)]
    pub yes: bool,
    /// Clear an emergency stop the device has latched (Ctrl-C, `lightrig stop`, its stop
    /// input) without asking: a person has seen to the rig. Without it the stop is cleared
    /// only when a person answers at the terminal (`--yes` does not clear it).
    #[arg(long)]
    pub clear_stop: bool,
    /// Go on even though the journal is damaged inside (intact records after the damage):
    /// drop it from the first damaged line, keeping the dropped bytes in
    /// journal.jsonl.dropped.N. Without it such a session is refused, to be looked at first.
    #[arg(long)]
    pub drop_damaged_tail: bool,
    /// The overrides the session was started with (`acquire --set`), for `--rig`'s check.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<Override>,
    /// On a finished session: acquire again every step whose frames went missing (the camera
    /// lost them at every try). Each such step is run whole; its earlier attempt stays in the
    /// journal, superseded.
    #[arg(long)]
    pub retake_missing: bool,
    /// Where the run's live page and API (docs/live-api.md) are served: by default on
    /// 127.0.0.1:7878 (another free port if that one is taken, printed at start); an address
    /// other than loopback needs the token printed at start.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = lightrig_serve::DEFAULT_ADDR)]
    pub serve: Option<String>,
    /// Serve no live page or API.
    #[arg(long, conflicts_with = "serve")]
    pub no_serve: bool,
}

pub(crate) fn connect_spec(rig: &RigFile, over: Option<&Connect>) -> Connect {
    over.cloned().unwrap_or_else(|| match &rig.connect {
        rigfile::Connect::Virtual => Connect::Virtual,
        rigfile::Connect::Serial { port, baud } => Connect::Serial { path: port.clone(), baud: *baud },
        rigfile::Connect::Usb => Connect::Usb { serial: None },
    })
}

/// Opens the link `spec` names. The virtual device is wired as the rig file says (switch
/// polarities, interlocks) and comes with its timeline, for a virtual camera to follow.
pub(crate) fn open(
    rig: &RigFile,
    spec: &Connect,
) -> Result<(Box<dyn Transport>, Option<Timeline>), CliError> {
    Ok(match spec {
        Connect::Virtual => {
            // A real camera beside the virtual controller takes its frames in real time: so
            // must the controller (the frames' wait is on its clock).
            let real_camera = rig.cameras.iter().any(|c| !matches!(c.source, FrameSource::Virtual { .. }));
            let (t, timeline) = connect_for_camera(rig, virtual_device_info(), real_camera);
            (Box::new(t), Some(timeline))
        }
        _ => (spec.open().map_err(|e| err(DEVICE, e.to_string()))?, None),
    })
}

/// Where a virtual camera writes its files inside a session directory (scratch: the session
/// stores its own copy of each frame; removed when the session completes).
pub const VIRTUAL_CAMERA_DIR: &str = "virtual-camera";

/// The frame inputs of the rig's cameras, as one. A virtual camera renders
/// [`scene_for`] the rig into `session/virtual-camera/camN/`, following the
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
            FrameSource::Genicam(g) => {
                lightrig_genicam::open(cam.camera, g, cam.min_interval_us).map_err(|e| err(DEVICE, e))?
            }
            FrameSource::Virtual { gamma } => {
                let dir = scratch.join(format!("cam{}", cam.camera));
                let (scene, mut sensor) = scene_for(rig, 1 + u64::from(cam.camera));
                sensor.response = lightrig_sim::sensor::Response::of_gamma(*gamma);
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
        match &cam.source {
            FrameSource::Directory { dir, pattern } => {
                DirectoryInput::new(cam.camera, dir, pattern).map_err(|e| err(INPUT, e))?;
            }
            FrameSource::Virtual { .. } => {
                let differs = lightrig_sim::scenes::unsimulated(rig);
                if !differs.is_empty() {
                    return Err(err(
                        INPUT,
                        format!(
                            "{}: camera {} is virtual, and the virtual rig renders its own fixed scene \
                             (docs/virtual-rig.md), not what [plan.fit] describes: {}. The fit would be told \
                             a camera and geometry the frames were not made with: acquire with the rig's own \
                             camera, or give [plan.fit] the virtual rig's values (docs/rigs/lls-gantry.toml \
                             has them) to try the file on the virtual rig",
                            rig.path.display(),
                            cam.camera,
                            differs.join("; ")
                        ),
                    ));
                }
            }
            FrameSource::Genicam(g) if !lightrig_genicam::available() => {
                return Err(err(
                    INPUT,
                    format!(
                        "{}: camera {} ({}): {}",
                        rig.path.display(),
                        cam.camera,
                        g.address,
                        lightrig_genicam::NOT_BUILT
                    ),
                ));
            }
            _ => {}
        }
    }
    Ok(())
}

/// How `acquire` and `resume` meet what a step asks of the host ([`acquire::step_requests`])
/// and a fault the device has latched: on the virtual rig its instruments do it and any fault
/// is cleared; else a person is asked at the terminal, or with `--yes` it is taken as done (a
/// scripted run on a rig set up beforehand).
#[derive(Debug, Clone)]
pub struct OperatorPrompt {
    /// The device is the virtual rig.
    pub virtual_rig: bool,
    /// `--yes`.
    pub assume_done: bool,
    /// `--clear-stop`.
    pub clear_stop: bool,
    /// Bringing a lost device back mid-run: an emergency stop found then was meant for this
    /// run (another terminal's `lightrig stop`, the board's stop input) and is never cleared.
    pub reconnecting: bool,
    /// Ctrl-C: the client stops the device.
    pub interrupt: Option<Arc<Interrupt>>,
}

/// Asks `question` at the terminal; `Ok(None)` when there is no terminal to ask at.
fn ask(question: &str) -> Result<Option<String>, String> {
    use std::io::{BufRead, IsTerminal};
    let stdin = std::io::stdin();
    if !stdin.is_terminal() {
        return Ok(None);
    }
    eprint!("{question}");
    let mut line = String::new();
    stdin.lock().read_line(&mut line).map_err(|e| format!("reading the answer: {e}"))?;
    Ok(Some(line.trim().to_string()))
}

impl StepPreparation for OperatorPrompt {
    fn prepare(&mut self, step: &Step, requests: &[String]) -> Result<String, String> {
        let list = requests.join("; ");
        if self.virtual_rig {
            eprintln!("\nstep {} ({}): the virtual rig does: {list}", step.id, step.name);
            return Ok("virtual".into());
        }
        eprintln!("\nstep {} ({}) needs (lasers disarmed until you are done):", step.id, step.name);
        for r in requests {
            eprintln!("  - {r}");
        }
        if self.assume_done {
            eprintln!("  (--yes: taken as done)");
            return Ok("assumed".into());
        }
        match ask("press Enter when done (q, Enter: stop here): ")? {
            None => Err(format!(
                "step {} ({}) needs a person: {list}. Run `lightrig resume` in a terminal to be asked, \
                 or pass --yes if the rig is already set up that way",
                step.id, step.name
            )),
            Some(a) if a.eq_ignore_ascii_case("q") => {
                Err(format!("stopped by the operator before step {} ({})", step.id, step.name))
            }
            Some(_) => Ok("operator".into()),
        }
    }
}

impl BringUpHooks for OperatorPrompt {
    fn say(&mut self, what: &str) {
        eprintln!("{what}");
    }

    fn may_clear(&mut self, cause: &FaultCause) -> bool {
        let stop = *cause == FaultCause::EmergencyStop;
        if !acquire::needs_a_person(cause) || (self.virtual_rig && !stop) {
            return true;
        }
        eprintln!("the device has latched a fault: {}", describe_fault(cause));
        if stop && self.reconnecting {
            eprintln!("  (found while bringing the lost device back: it stops this run)");
            return false;
        }
        if stop && self.clear_stop {
            eprintln!("  (--clear-stop: a person has seen to the rig; clearing it)");
            return true;
        }
        if self.assume_done && !stop {
            eprintln!("  (--yes: taken as seen to; clearing it)");
            return true;
        }
        match ask("has a person seen to it, so that it is safe to clear? (yes, Enter / anything else: no) ") {
            Ok(Some(a)) => a.eq_ignore_ascii_case("yes") || a.eq_ignore_ascii_case("y"),
            _ => false,
        }
    }

    fn interrupt(&self) -> Option<Arc<Interrupt>> {
        self.interrupt.clone()
    }
}

/// Ctrl-C during `acquire` or `resume`: the first asks the client to send `EmergencyStop` and
/// lets the run end (its step abandoned, to be acquired again by `lightrig resume`, which asks
/// a person before it clears the stop). If the run has not ended 5 s after the stop went out
/// (a prompt waiting on the terminal), the process ends with code 130; a second Ctrl-C ends it
/// at once, but only once the stop has gone out. The device is safe either way.
pub(crate) fn on_ctrl_c() -> Option<Arc<Interrupt>> {
    on_ctrl_c_of(Arc::new(Interrupt::default()))
}

/// [`on_ctrl_c`] asking `interrupt`, which other stop requests (the control socket) share: a
/// stop from there ends the process on the same terms.
pub(crate) fn on_ctrl_c_of(interrupt: Arc<Interrupt>) -> Option<Arc<Interrupt>> {
    let i = interrupt.clone();
    let installed = ctrlc::set_handler(move || {
        if i.requested() && i.stopped() {
            std::process::exit(130);
        }
        if i.requested() {
            eprintln!("\nCtrl-C: still sending the stop to the device…");
            return;
        }
        eprintln!("\nCtrl-C: stopping the device (EmergencyStop)…");
        i.request();
    });
    let i = interrupt.clone();
    std::thread::spawn(move || {
        let tick = std::time::Duration::from_millis(20);
        while !i.requested() {
            std::thread::sleep(tick);
        }
        // The run's next turn of the link sends the stop (at most one heartbeat wait away).
        for _ in 0..100 {
            if i.stopped() {
                break;
            }
            std::thread::sleep(tick);
        }
        std::thread::sleep(std::time::Duration::from_secs(5));
        std::process::exit(130);
    });
    installed.is_ok().then_some(interrupt)
}

struct Boxed<'a>(&'a mut dyn FrameInput);

impl FrameInput for Boxed<'_> {
    fn begin_step(&mut self, step: &Step) -> std::io::Result<()> {
        self.0.begin_step(step)
    }
    fn on_trigger(&mut self, t: &TriggerEvent, h: Option<f64>) -> std::io::Result<()> {
        self.0.on_trigger(t, h)
    }
    fn poll(&mut self, now: f64) -> std::io::Result<Vec<Captured>> {
        self.0.poll(now)
    }
    fn poll_now(&mut self, now: f64) -> std::io::Result<Vec<Captured>> {
        self.0.poll_now(now)
    }
    fn stamps_follow_triggers(&self) -> bool {
        self.0.stamps_follow_triggers()
    }
    fn backlog(&self) -> usize {
        self.0.backlog()
    }
    fn lost(&mut self) -> Vec<(u8, u32, String)> {
        self.0.lost()
    }
}

fn print_summary(plan: &Plan, info: &DeviceInfo) {
    let s = plan.summary();
    eprintln!(
        "plan: {} ({} steps, {} frames, at least {:.0} s of device time; {} at {} a frame by [plan] frame_bytes, \
         the progress line gives the size the frames take) on {:?} at {} Hz",
        plan.method,
        s.steps,
        s.triggers,
        s.min_duration_us as f64 / 1e6,
        bytes_in_words(s.bytes as f64),
        bytes_in_words(plan.frame_bytes as f64),
        info.board,
        info.tick_hz
    );
    // The bispectral plan's optical exposure (the thesis counts cost in it), steered or not.
    if let (Some(t), Some(dense)) =
        (plan.meta["optical_exposure_s"].as_f64(), plan.meta["dense_optical_exposure_s"].as_f64())
    {
        eprintln!(
            "optical exposure {:.1} h; every pair at every angle would take {:.1} h ({:.0} %)",
            t / 3600.0,
            dense / 3600.0,
            100.0 * t / dense.max(1e-9)
        );
    }
}

/// One status line, rewritten in place at most ten times a second ([`progress_line`]).
fn progress_printer() -> impl FnMut(Progress) {
    let mut last: Option<std::time::Instant> = None;
    // The run's pace is measured from its first report (the first step's start), not from
    // the bring-up and homing before it.
    let mut began: Option<std::time::Instant> = None;
    move |p: Progress| {
        // Frames gone missing are said at once, on a line of their own.
        if let Some(what) = &p.missing_now {
            eprintln!("\nwarning: {what}");
        }
        let now = std::time::Instant::now();
        let began = *began.get_or_insert(now);
        let recent = last.is_some_and(|l| now.duration_since(l).as_millis() < 100);
        if recent && p.triggered < p.to_trigger && p.missing_now.is_none() {
            return;
        }
        last = Some(now);
        eprint!("\r{}   ", progress_line(&p, now.duration_since(began).as_secs_f64()));
    }
}

/// The status line of `p`, `elapsed_s` into the run's steps: triggers fired of those to
/// fire, frames stored and received, the trigger rate, the data stored and what the whole run
/// will take at that size a frame, and the time left: the plan's own estimate of the work left
/// scaled by the pace so far (the plan's times are lower bounds: every wait ending at once),
/// or before any work is done, the plan's bound itself.
pub fn progress_line(p: &Progress, elapsed_s: f64) -> String {
    let bar = (20 * p.triggered / p.to_trigger.max(1)).min(20) as usize;
    let missing = if p.missing > 0 { format!(", {} MISSING", p.missing) } else { String::new() };
    let received = if p.received > 0 { format!(" (+{} received)", p.received) } else { String::new() };
    let rate = if elapsed_s > 0.0 { p.triggered as f64 / elapsed_s } else { 0.0 };
    let size = if p.frames > 0 {
        let all = p.bytes as f64 / p.frames as f64 * p.to_trigger as f64;
        format!("  {} stored, about {} in all", bytes_in_words(p.bytes as f64), bytes_in_words(all))
    } else {
        String::new()
    };
    let eta = match p.time_left_s(elapsed_s) {
        (left_s, false) => format!("ETA {left_s:.0} s"),
        (left_s, true) => format!("ETA ≥ {left_s:.0} s (plan)"),
    };
    format!(
        "[{}{}] step {}/{}  {}/{} triggers  {} frames stored{received}{missing}  {:.1} triggers/s{size}  {eta}",
        "=".repeat(bar),
        " ".repeat(20 - bar),
        p.steps_done,
        p.steps,
        p.triggered,
        p.to_trigger,
        p.frames,
        rate,
    )
}

/// `bytes` as kB, MB or GB (powers of ten), one decimal.
fn bytes_in_words(bytes: f64) -> String {
    match bytes {
        b if b >= 1e9 => format!("{:.1} GB", b / 1e9),
        b if b >= 1e6 => format!("{:.1} MB", b / 1e6),
        b => format!("{:.1} kB", b / 1e3),
    }
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
    // A real device that goes away (unplug, port reset) is waited for and brought up again;
    // the virtual one lives in this process and cannot.
    let attempts = if *spec == Connect::Virtual { 0 } else { RECONNECT_ATTEMPTS };
    let mut hooks = OperatorPrompt { reconnecting: true, ..prep.clone() };
    let interrupt = prep.interrupt.clone();
    // Tunable filters the rig file gives ports for are tuned by the host, the rest asked (on
    // the virtual rig without ports, its instruments follow the step's meta by themselves).
    let filters = lightrig_host::filter::from_rig(rig).map_err(|e| err(INPUT, e.to_string()))?;
    let mut tuned;
    let steps: &mut dyn acquire::StepPreparation = if filters.is_empty() {
        prep
    } else {
        tuned = lightrig_host::filter::FilterPreparation { filters, rest: Box::new(prep.clone()) };
        &mut tuned
    };
    let mut reconnect = |old: Option<Box<dyn Transport>>, k: u32| {
        // Close the old port before opening it again. The wait ends early at Ctrl-C: bring-up
        // then sends the stop the lost link could not.
        drop(old);
        let until = std::time::Instant::now() + std::time::Duration::from_millis(reconnect_backoff_ms(k));
        while std::time::Instant::now() < until && !interrupt.as_ref().is_some_and(|i| i.requested()) {
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let (t, _) = open(rig, spec).map_err(|e| client_error(spec, e))?;
        bring_up_with(rig, t, &mut hooks).map_err(|e| match e {
            lightrig_host::bringup::BringUpError::Client(e) => e,
            other => client_error(spec, other.into()),
        })
    };
    let r = acquire::run_reconnecting(
        client,
        &mut reconnect,
        attempts,
        session,
        plan,
        &mut Boxed(input),
        steps,
        progress_printer(),
        |m| eprintln!("\n{m}"),
    );
    eprintln!();
    r.map_err(|e| match e {
        acquire::AcquireError::Preparation(_) => err(FAILURE, e.to_string()),
        acquire::AcquireError::Device(ClientError::Interrupted { .. }) => err(INTERRUPTED, e.to_string()),
        _ => err(DEVICE, e.to_string()),
    })?;
    let scratch = session.dir().join(VIRTUAL_CAMERA_DIR);
    if scratch.exists() {
        std::fs::remove_dir_all(&scratch).map_err(|e| err(FAILURE, format!("{}: {e}", scratch.display())))?;
    }
    eprintln!("session complete: {}", session.dir().display());
    eprintln!("{}", tally(session));
    incomplete(session)
}

/// A finished session that still misses frames is no success: exit code [`INCOMPLETE`], the
/// steps named, and how to acquire them again.
fn incomplete(session: &Session) -> Result<(), CliError> {
    match session.missing_report() {
        None => Ok(()),
        Some(report) => Err(err(
            INCOMPLETE,
            format!("{}: the session is complete, with {report}", session.dir().display()),
        )),
    }
}

/// What the session holds, in words: frames, missing frames, and frames without a trigger by
/// why (a shift in a camera's numbering shows as those).
fn tally(session: &Session) -> String {
    use lightrig_host::session::{ExtraReason, Outcome};
    let st = session.state();
    let (mut frames, mut missing, mut duplicate, mut no_trigger, mut before) = (0, 0, 0, 0, 0);
    for step in st.steps_done() {
        let (_, a) = st.done_attempt(step).expect("a done step has its attempt");
        frames += a.frames.len();
        missing += a.missing.len();
        for x in &a.extra {
            match x.reason {
                ExtraReason::Duplicate => duplicate += 1,
                ExtraReason::NoTrigger => no_trigger += 1,
                ExtraReason::BeforeStep => before += 1,
            }
        }
    }
    let mut out = format!("  {frames} frames paired with their triggers, {missing} missing");
    // Attempts given up because their camera lost frames (the steps acquired again).
    let retried: Vec<String> = st
        .steps
        .iter()
        .flat_map(|(step, attempts)| {
            attempts.values().filter_map(move |a| match &a.outcome {
                Outcome::Abandoned { reason } if reason.starts_with(acquire::LOST_PREFIX) => {
                    Some(format!("step {step}: {reason}"))
                }
                _ => None,
            })
        })
        .collect();
    if !retried.is_empty() {
        out += &format!("\n  {} step attempt(s) lost frames and were acquired again:", retried.len());
        for r in retried.iter().take(5) {
            out += &format!("\n    {r}");
        }
        if retried.len() > 5 {
            out += &format!("\n    … and {} more (the journal's StepAbandoned records)", retried.len() - 5);
        }
    }
    if duplicate > 0 {
        out += &format!("\n  {duplicate} duplicate frames (a trigger's second frame), kept as extra-* files");
    }
    if before > 0 {
        out += &format!(
            "\n  {before} frames made before their step began (stragglers of a cut-short attempt), kept \
             as extra-* files and not paired"
        );
    }
    if no_trigger > 0 {
        out += &format!(
            "\n  {no_trigger} frames matched no trigger, kept as extra-* files: if a camera's files were \
             numbered on from an earlier shot, that step's frames may be shifted; compare the extra \
             files with their neighbours"
        );
    }
    for line in camera_clock_check(session) {
        out += &format!("\n  {line}");
    }
    out
}

/// Per step and line-triggered camera that stamps its frames (GenICam): the camera's
/// timestamps against the trigger ticks they were paired with. A frame more than a quarter of
/// the trigger spacing (and 1 ms) off the line the others make was likely paired with the
/// wrong trigger: named. (A software-triggered camera's times carry the host's latency and,
/// on Aravis's fake camera, its frame clock's 40 ms steps: not checked.)
fn camera_clock_check(session: &Session) -> Vec<String> {
    let st = session.state();
    let mut out = Vec::new();
    let rig = RigFile::parse(&session.manifest().rig, &session.dir().join("manifest.json")).ok();
    let line_triggered = |cam: u8| {
        rig.as_ref().and_then(|r| r.cameras.iter().find(|c| c.camera == cam)).is_some_and(
            |c| matches!(&c.source, FrameSource::Genicam(g) if !g.trigger.eq_ignore_ascii_case("software")),
        )
    };
    for step in st.steps_done() {
        let (_, a) = st.done_attempt(step).expect("a done step has its attempt");
        let cameras: std::collections::BTreeSet<u8> = a.frames.keys().map(|k| k.0).collect();
        for cam in cameras.into_iter().filter(|&c| line_triggered(c)) {
            let frames: Vec<_> = a.frames.range((cam, 0)..=(cam, u32::MAX)).map(|(_, f)| f).collect();
            let pts: Vec<(u64, u64)> =
                frames.iter().filter_map(|f| f.camera_stamp.map(|c| (f.tick, c.time_ns))).collect();
            let stamped: Vec<_> = frames.iter().filter(|f| f.camera_stamp.is_some()).collect();
            let off: Vec<String> = lightrig_host::session::off_their_triggers(&pts)
                .into_iter()
                .map(|(k, r)| format!("frame {} ({:+.1} ms)", stamped[k].frame, r / 1e6))
                .collect();
            if !off.is_empty() {
                out.push(format!(
                    "step {step}, camera {cam}: the camera's timestamps put {} off their triggers' ticks; \
                     those frames may be paired with the wrong trigger",
                    off.join(", ")
                ));
            }
        }
    }
    out
}

/// A bring-up failure during reconnection, as the client error the engine reports.
fn client_error(spec: &Connect, e: CliError) -> ClientError {
    ClientError::Io { device: spec.to_string(), error: std::io::Error::other(e.message) }
}

/// The rig file at `path` with `overrides` applied: its text and the parsed file.
pub fn rig_with(path: &Path, overrides: &[Override]) -> Result<(String, RigFile), CliError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| err(INPUT, format!("{}: cannot read the rig file: {e}", path.display())))?;
    let text =
        overrides::apply(&text, overrides).map_err(|e| err(INPUT, format!("{}: {e}", path.display())))?;
    let rig = RigFile::parse(&text, path).map_err(|e| err(INPUT, e.to_string()))?;
    Ok((text, rig))
}

/// What the operator said on the command line a run may take as done.
#[derive(Debug, Clone, Copy)]
struct Consent {
    /// `--yes`.
    yes: bool,
    /// `--clear-stop`.
    clear_stop: bool,
}

/// `lightrig acquire RIG --session DIR [--yes] [--clear-stop] [--set KEY=VALUE …]`.
pub fn acquire(args: &AcquireArgs) -> Result<(), CliError> {
    let (rig_path, dir, over, overrides) =
        (args.rig.as_path(), args.session.as_path(), args.connect.as_ref(), &args.overrides[..]);
    let consent = Consent { yes: args.yes, clear_stop: args.clear_stop };
    let (text, rig) = rig_with(rig_path, overrides)?;
    // Everything that needs no device, before anything connects or moves: the keys, every
    // plan value against its range and the steppers' limits, the fit's [plan.fit].
    from_rig::check(&rig).map_err(|e| err(INPUT, e.to_string()))?;
    if let Some(warning) = lightrig_host::fit::check_rig(&rig).map_err(|e| err(INPUT, e.0))? {
        eprintln!("warning: {warning}");
    }
    lightrig_host::response::check(&rig).map_err(|e| err(INPUT, e))?;
    if dir.join("manifest.json").exists() {
        return Err(err(
            INPUT,
            format!("{} already holds a session; continue it with `lightrig resume {0}`", dir.display()),
        ));
    }
    let ready = bring_up(&rig, over, consent, "acquire", dir, serving(&args.serve, args.no_serve))?;
    let manifest = Manifest::new(text, ready.client.info(), plan_summary(&ready.plan));
    let mut session = Session::create(dir, manifest).map_err(|e| err(INPUT, e.to_string()))?;
    lightrig_host::response::attach(&rig, dir).map_err(|e| err(INPUT, e))?;
    ready.run(&rig, &mut session)
}

/// `lightrig resume DIR [--rig RIG] [--yes] [--drop-damaged-tail]`: the session's own rig file (the copy in its
/// manifest; `rig` says where the original lives, for its relative paths, and must be
/// unchanged), planned again and checked against the manifest, then the steps not yet done.
pub fn resume(args: &ResumeArgs) -> Result<(), CliError> {
    let (dir, rig_path, over) = (args.session.as_path(), args.rig.as_deref(), args.connect.as_ref());
    let consent = Consent { yes: args.yes, clear_stop: args.clear_stop };
    let opened = if args.drop_damaged_tail { Session::open_dropping_damage(dir) } else { Session::open(dir) };
    let (mut session, recovery) = opened.map_err(|e| err(INPUT, e.to_string()))?;
    eprintln!("resuming {}: {recovery}", dir.display());
    let retake = session.is_done() && args.retake_missing;
    if session.is_done() {
        let missing = session.steps_missing_frames();
        if missing.is_empty() {
            eprintln!("{}: the session is already complete, every frame present", dir.display());
            return Ok(());
        }
        if !retake {
            return incomplete(&session);
        }
    }
    let text = session.manifest().rig.clone();
    let base: PathBuf = match rig_path {
        Some(p) => {
            let (now, _) = rig_with(p, &args.overrides)?;
            if now != text {
                return Err(err(
                    INPUT,
                    format!(
                        "{} with {} override(s) is not the rig file the session started with: resume with \
                         the original file and the same --set options (the session's copy is in its \
                         manifest.json)",
                        p.display(),
                        args.overrides.len()
                    ),
                ));
            }
            p.to_path_buf()
        }
        None => PathBuf::from("rig.toml"),
    };
    let rig = RigFile::parse(&text, &base).map_err(|e| err(INPUT, e.to_string()))?;
    let ready = bring_up(&rig, over, consent, "resume", dir, serving(&args.serve, args.no_serve))?;
    if !same_steps(&plan_summary(&ready.plan).steps, &session.manifest().plan.steps) {
        return Err(err(
            INPUT,
            "the rig file's plan no longer matches the session's (a different device tick rate or a changed \
             planner); finish it with the host version that started it",
        ));
    }
    if retake {
        let steps = session.reopen_missing().map_err(|e| err(INPUT, e.to_string()))?;
        eprintln!("retaking {} step(s) with missing frames: {steps:?}", steps.len());
    }
    ready.run(&rig, &mut session)
}

/// Where to serve the live endpoint, and whether the address was asked for (else the default,
/// which gives way to a free port when taken); `None` with `--no-serve`.
fn serving(serve: &Option<String>, no_serve: bool) -> Option<(&str, bool)> {
    match serve {
        _ if no_serve => None,
        Some(addr) => Some((addr.as_str(), true)),
        None => Some((lightrig_serve::DEFAULT_ADDR, false)),
    }
}

/// A rig brought up for `acquire` or `resume`: the device connected, configured and homed,
/// the plan made for it.
struct Ready {
    spec: Connect,
    prep: OperatorPrompt,
    client: Client<Box<dyn Transport>>,
    timeline: Option<Timeline>,
    plan: Plan,
    /// Served as long as the run lasts.
    _control: Control,
    /// `--serve`: the live endpoint, as long as the run lasts.
    served: Option<super::live::Served>,
}

/// Checks the rig's frame sources, connects where `over` (else the rig file) says, brings the
/// device up and plans.
fn bring_up(
    rig: &RigFile,
    over: Option<&Connect>,
    consent: Consent,
    run: &str,
    session: &Path,
    serve: Option<(&str, bool)>,
) -> Result<Ready, CliError> {
    check_sources(rig)?;
    let spec = connect_spec(rig, over);
    // Ctrl-C here and `lightrig stop` from another terminal (through the control socket) ask
    // the same stop.
    let interrupt = Arc::new(Interrupt::default());
    let mut prep = OperatorPrompt {
        virtual_rig: spec == Connect::Virtual,
        assume_done: consent.yes,
        clear_stop: consent.clear_stop,
        reconnecting: false,
        interrupt: on_ctrl_c_of(interrupt.clone()).or(Some(interrupt.clone())),
    };
    let start = |addr: &str| super::live::serve(addr, run, session, &spec.to_string(), interrupt.clone());
    let served = match serve {
        Some((addr, true)) => Some(start(addr)?),
        // The default port taken (another run serves there): any free one.
        Some((addr, false)) => Some(start(addr).or_else(|_| start("127.0.0.1:0"))?),
        None => None,
    };
    let (transport, timeline) = open(rig, &spec)?;
    let control = serve_control(&spec, interrupt, run, session, served.as_ref().map(|s| s.url.as_str()));
    let client = bring_up_with(rig, transport, &mut prep)?;
    let plan = from_rig::plan(rig, client.info()).map_err(|e| err(INPUT, e.to_string()))?;
    if let Some(s) = &served {
        s.live.set_method(&plan.method);
    }
    Ok(Ready { spec, prep, client, timeline, plan, _control: control, served })
}

/// The names under which `lightrig stop` finds the run holding the device `spec` names.
pub(crate) fn control_keys(spec: &Connect) -> Vec<String> {
    match spec {
        #[cfg(unix)]
        Connect::Serial { path, .. } => lightrig_host::control::port_keys(path),
        #[cfg(not(unix))]
        Connect::Serial { path, .. } => vec![path.clone()],
        // One in-process virtual rig per process.
        Connect::Virtual => vec![format!("virtual:{}", std::process::id())],
        Connect::Usb { serial } => vec![format!("usb:{}", serial.as_deref().unwrap_or(""))],
    }
}

/// The run's control socket ([`lightrig_host::control`]); a run without one still stops at
/// Ctrl-C, and says that `lightrig stop` will not reach it.
#[cfg(unix)]
type Control = Option<lightrig_host::control::ControlServer>;
#[cfg(not(unix))]
type Control = Option<()>;

fn serve_control(
    spec: &Connect,
    interrupt: Arc<Interrupt>,
    run: &str,
    session: &Path,
    live: Option<&str>,
) -> Control {
    #[cfg(unix)]
    {
        let mut about =
            format!("lightrig {run} (pid {}) on {spec}, session {}", std::process::id(), session.display());
        if let Some(url) = live {
            about += &format!(", live {url}");
        }
        match lightrig_host::control::ControlServer::serve(&control_keys(spec), interrupt, about) {
            Ok(c) => Some(c),
            Err(e) => {
                eprintln!(
                    "warning: no control socket ({e}): `lightrig stop` from another terminal cannot reach this \
                     run; Ctrl-C here still stops it"
                );
                None
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = (spec, interrupt, run, session, live);
        None
    }
}

impl Ready {
    /// Runs the plan's unfinished steps into `session`.
    fn run(mut self, rig: &RigFile, session: &mut Session) -> Result<(), CliError> {
        print_summary(&self.plan, self.client.info());
        let tick_hz = self.client.info().tick_hz;
        let mut input = frame_input(rig, session.dir(), self.timeline.take(), tick_hz)?;
        if let Some(s) = &self.served {
            s.attach(session, &mut self.client);
        }
        let result = run(self.client, rig, &self.spec, session, &self.plan, input.as_mut(), &mut self.prep);
        if let Some(s) = &self.served {
            s.ended(&result);
        }
        result
    }
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

    fn at(triggered: u64, frames: u64, received: u64, bytes: u64, done_us: u64, left_us: u64) -> Progress {
        Progress {
            steps_done: 1,
            steps: 3,
            frames,
            received,
            bytes,
            planned_done_us: done_us,
            planned_left_us: left_us,
            triggered,
            to_trigger: 486,
            missing: 0,
            missing_now: None,
        }
    }

    /// Before any work the time left is the plan's bound; after it, the plan's estimate at
    /// the run's own pace (here 3.7 × the plan's times, as the 21 s plan that took
    /// 78 s); the size is what the stored frames take a frame, times the run's frames.
    #[test]
    fn the_progress_line_counts_frames_as_they_come_and_times_the_rest_by_the_run_s_pace() {
        assert_eq!(
            progress_line(&at(0, 0, 0, 0, 0, 21_000_000), 0.0),
            "[                    ] step 1/3  0/486 triggers  0 frames stored  0.0 triggers/s  ETA ≥ 21 s (plan)"
        );
        // 243 triggers in 39 s for 10.5 s of the plan's 21: 10.5 s left at 3.71 × = 39 s.
        assert_eq!(
            progress_line(&at(243, 200, 43, 8_800_000, 10_500_000, 10_500_000), 39.0),
            "[==========          ] step 1/3  243/486 triggers  200 frames stored (+43 received)  6.2 triggers/s  \
             8.8 MB stored, about 21.4 MB in all  ETA 39 s"
        );
        let mut lost = at(486, 244, 0, 10_736_000, 21_000_000, 0);
        lost.missing = 242;
        assert!(progress_line(&lost, 78.0).contains("244 frames stored, 242 MISSING  6.2 triggers/s"));
        assert!(progress_line(&lost, 78.0).ends_with("ETA 0 s"));
    }
}
