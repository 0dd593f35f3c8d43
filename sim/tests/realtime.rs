//! The host against a controller that keeps its own time, as a real board does: the virtual
//! controller behind a pseudo-terminal ([`PtyRig`]) on its own thread, paced by the wall clock,
//! reached through the host's real serial transport. While the host is busy elsewhere (a person
//! at a prompt, frames read from disk) the device's heartbeat watchdog keeps counting; the
//! host must keep the link alive meanwhile. These tests run in real time: each waits on I/O or
//! on the host's own work, never for a fixed time to pass on the device.
#![cfg(unix)]

mod common;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use lightrig_firmware::sim::{virtual_device_info, SimBoard};
use lightrig_host::acquire::{self, plan_summary, Captured, FrameInput, StepPreparation};
use lightrig_host::bringup::{bring_up_with, BringUpHooks};
use lightrig_host::client::Client;
use lightrig_host::plan::{lls, Plan, Step};
use lightrig_host::rigfile::RigFile;
use lightrig_host::session::{journal_records, Manifest, Record, Session};
use lightrig_host::transport::SerialTransport;
use lightrig_protocol::config::{ConfigItem, SafetyConfig};
use lightrig_protocol::event::{Event, TriggerEvent};
use lightrig_protocol::Command;
use lightrig_sim::board::board_for;
use lightrig_sim::pty::PtyRig;

/// The device's heartbeat timeout in these tests, µs (the shipped LLS rig file's).
const HEARTBEAT_TIMEOUT_US: u64 = 200_000;
/// How long the host is busy at a time: well past the timeout.
const BUSY: Duration = Duration::from_millis(700);

/// A [`PtyRig`] serving on its own thread until dropped.
struct RealTimeRig {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl RealTimeRig {
    fn start() -> Self {
        Self::wired(None)
    }

    /// The controller on a board wired as `rig` says (a bare one for `None`).
    fn wired(rig: Option<RigFile>) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, rx) = mpsc::channel();
        let s = stop.clone();
        // The controller holds its simulated clock in an `Rc`: it is made on its own thread.
        let thread = std::thread::spawn(move || {
            let board = rig.as_ref().map_or_else(SimBoard::default, board_for);
            let mut rig = PtyRig::open(virtual_device_info(), board).unwrap();
            tx.send(rig.path().to_path_buf()).unwrap();
            rig.serve(|| s.load(Ordering::SeqCst)).unwrap();
        });
        let path = rx.recv().unwrap();
        Self { path, stop, thread: Some(thread) }
    }
}

impl Drop for RealTimeRig {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A person who takes [`BUSY`] at every step that asks for one.
struct SlowPerson;

impl StepPreparation for SlowPerson {
    fn prepare(&mut self, _step: &Step, _requests: &[String]) -> Result<String, String> {
        std::thread::sleep(BUSY);
        Ok("operator".into())
    }
}

/// A camera whose frames take [`BUSY`] to read (large files on a slow disk): one frame per
/// trigger, handed over only when the engine polls, each poll with frames slow.
#[derive(Default)]
struct SlowCamera {
    ready: Vec<Captured>,
    /// Reading frames takes no time (frames from memory).
    quick: bool,
    /// Each step begins with [`BUSY`] of the camera's own (new settings taken, a directory
    /// looked through), and so does every look for frames, even when there are none.
    slow_between_steps: bool,
}

impl FrameInput for SlowCamera {
    fn begin_step(&mut self, _step: &Step) -> std::io::Result<()> {
        if self.slow_between_steps {
            std::thread::sleep(BUSY);
        }
        Ok(())
    }

    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        self.ready.push(Captured {
            camera: t.camera,
            frame: Some(t.frame),
            ext: "txt".into(),
            data: format!("frame {}\n", t.frame).into_bytes(),
            host_us: host_us.unwrap_or(0.0) + 500.0,
            before_step: false,
            stamp: None,
        });
        Ok(())
    }

    fn poll(&mut self, _now: f64) -> std::io::Result<Vec<Captured>> {
        if !self.ready.is_empty() && !self.quick || self.slow_between_steps {
            std::thread::sleep(BUSY);
        }
        Ok(std::mem::take(&mut self.ready))
    }
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lightrig-rt-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// A short LLS plan (3 passes of 4 positions) whose second step asks for a person.
fn plan_with_a_prompt() -> Plan {
    let mut p = common::lls_params();
    p.count = 4;
    let mut plan = lls::plan(&p).unwrap();
    plan.steps[1].meta["operator"] = "turn the light's mount".into();
    plan
}

fn connect(rig: &RealTimeRig) -> Client<SerialTransport> {
    let port = SerialTransport::open(rig.path.to_str().unwrap(), 115_200).unwrap();
    let mut c = common::setup(Client::connect(port, 0x5eed).unwrap());
    let safety = SafetyConfig { heartbeat_timeout_ticks: HEARTBEAT_TIMEOUT_US as u32 };
    c.request(Command::Configure(ConfigItem::Safety(safety))).unwrap();
    c.set_heartbeat_us(HEARTBEAT_TIMEOUT_US / 4);
    c
}

/// The journal's `State` events: (tick, armed lasers).
fn armed_states(dir: &Path) -> Vec<(u64, u8)> {
    journal_records(dir)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            Record::Event { event: Event::State { armed, tick, .. }, .. } => Some((tick, armed)),
            _ => None,
        })
        .collect()
}

/// The journal's `Fault` events.
fn faults(dir: &Path) -> Vec<Record> {
    journal_records(dir)
        .unwrap()
        .into_iter()
        .filter(|r| matches!(r, Record::Event { event: Event::Fault { .. }, .. }))
        .collect()
}

/// The session is done with one frame for every trigger of every step.
fn assert_every_frame(session: &Session, plan: &Plan) {
    assert!(session.is_done());
    for step in &plan.steps {
        assert_eq!(session.frames_of(step.id).len(), step.shot_count(), "step {}", step.id);
    }
}

#[test]
fn a_person_at_a_prompt_and_slow_frame_reads_do_not_time_the_host_out() {
    let rig = RealTimeRig::start();
    let dir = temp_dir("busy");
    let plan = plan_with_a_prompt();
    let mut client = connect(&rig);
    let mut session =
        Session::create(&dir, Manifest::new("# test rig", client.info(), plan_summary(&plan))).unwrap();
    let started = Instant::now();
    acquire::run_prepared(
        &mut client,
        &mut session,
        &plan,
        &mut SlowCamera::default(),
        &mut SlowPerson,
        |_| {},
    )
    .unwrap();
    // The host was busy far longer than the device's heartbeat timeout, several times over.
    assert!(started.elapsed() > 4 * BUSY, "{:?}", started.elapsed());
    assert_every_frame(&session, &plan);
    let faults = faults(&dir);
    assert_eq!(faults, vec![], "no fault while the host was busy");
    // The lasers were disarmed for the whole time the person was at the rig: disarmed before
    // the prompt, armed again only after it, at least BUSY later on the device's clock.
    let states = armed_states(&dir);
    let disarmed_for = states
        .windows(2)
        .filter(|w| w[0].1 == 0 && w[1].1 != 0)
        .map(|w| w[1].0 - w[0].0)
        .max()
        .expect("a disarm followed by an arm");
    assert!(disarmed_for >= BUSY.as_micros() as u64, "disarmed for {disarmed_for} ticks only: {states:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_slow_disk_does_not_time_the_host_out() {
    let rig = RealTimeRig::start();
    let dir = temp_dir("slow-disk");
    let mut p = common::lls_params();
    p.count = 2;
    let plan = lls::plan(&p).unwrap();
    let mut client = connect(&rig);
    let mut session =
        Session::create(&dir, Manifest::new("# test rig", client.info(), plan_summary(&plan))).unwrap();
    // Every fsync (journal records, frame files, events) takes longer than the heartbeat
    // timeout.
    let delay = Duration::from_micros(HEARTBEAT_TIMEOUT_US * 5 / 4);
    session.simulate_slow_disk(delay);
    let started = Instant::now();
    acquire::run(
        &mut client,
        &mut session,
        &plan,
        &mut SlowCamera { quick: true, ..Default::default() },
        |_| {},
    )
    .unwrap();
    assert!(started.elapsed() > 10 * delay, "the disk was slow: {:?}", started.elapsed());
    assert_every_frame(&session, &plan);
    drop(session);
    let faults = faults(&dir);
    assert_eq!(faults, vec![], "no fault while the disk was slow");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A camera slow between steps (its settings, its directory) leaves the host as alive as one
/// slow with its frames: no step boundary is a silence the device times out (issue 60: over
/// `sim --pty` a step's `SequenceLoad` was refused with `Faulted(HeartbeatLost)`).
#[test]
fn a_camera_slow_between_steps_does_not_time_the_host_out() {
    let rig = RealTimeRig::start();
    let dir = temp_dir("between");
    let mut p = common::lls_params();
    p.count = 2;
    let plan = lls::plan(&p).unwrap();
    let mut client = connect(&rig);
    let mut session =
        Session::create(&dir, Manifest::new("# test rig", client.info(), plan_summary(&plan))).unwrap();
    let mut camera = SlowCamera { quick: true, slow_between_steps: true, ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut camera, |_| {}).unwrap();
    assert_every_frame(&session, &plan);
    drop(session);
    let faults = faults(&dir);
    assert_eq!(faults, vec![], "no fault between the steps");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A camera that makes its first frame of each step slowly, longer than the engine's wait
/// for a frame ([`acquire::FRAME_WAIT_US`]), then keeps up (a render or a conversion that
/// falls behind the trigger rate), run on a thread of its own as the CLI runs its cameras.
struct LaggingCamera {
    inner: SlowCamera,
    first: bool,
}

impl FrameInput for LaggingCamera {
    fn begin_step(&mut self, step: &Step) -> std::io::Result<()> {
        self.first = true;
        self.inner.begin_step(step)
    }
    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        if std::mem::take(&mut self.first) {
            std::thread::sleep(Duration::from_micros(acquire::FRAME_WAIT_US * 3 / 2));
        }
        self.inner.on_trigger(t, host_us)
    }
    fn poll(&mut self, now: f64) -> std::io::Result<Vec<Captured>> {
        self.inner.poll(now)
    }
}

#[test]
fn a_camera_behind_the_triggers_is_waited_for_while_it_works_through_them() {
    let rig = RealTimeRig::start();
    let dir = temp_dir("lagging");
    let mut p = common::lls_params();
    p.count = 3;
    let mut plan = lls::plan(&p).unwrap();
    // Its frames are lost for good at the first try (no retry), if they are lost.
    plan.lost_retries = 0;
    plan.steps.truncate(1);
    let mut client = connect(&rig);
    let mut session =
        Session::create(&dir, Manifest::new("# test rig", client.info(), plan_summary(&plan))).unwrap();
    let camera = LaggingCamera { inner: SlowCamera { quick: true, ..Default::default() }, first: false };
    let mut input = acquire::Background::new(Box::new(camera));
    acquire::run(&mut client, &mut session, &plan, &mut input, |_| {}).unwrap();
    // The sequence was over long before the first frame came, and no frame came for longer
    // than the wait: the backlog kept the engine waiting, and every frame is there.
    assert_eq!(session.steps_missing_frames(), vec![], "no frame missing");
    assert_eq!(session.frames_of(plan.steps[0].id).len(), plan.steps[0].shot_count());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A gantry that homes in well under a second, with the shipped LLS rig's 200 ms heartbeat.
const QUICK_RIG: &str = include_str!("support/prompting-gantry.toml");

/// Bring-up's words, kept.
#[derive(Default)]
struct Heard(Vec<String>);

impl BringUpHooks for Heard {
    fn say(&mut self, what: &str) {
        self.0.push(what.to_string());
    }
}

#[test]
fn a_fault_latched_while_no_host_was_there_is_cleared_and_named_not_read_as_a_homing_failure() {
    let rig_file = RigFile::parse(QUICK_RIG, Path::new("quick.toml")).unwrap();
    let rig = RealTimeRig::wired(Some(rig_file.clone()));
    let port = || Box::new(SerialTransport::open(rig.path.to_str().unwrap(), 115_200).unwrap());
    // A first host (`lightrig info`, or an acquisition that stopped at a prompt) sets a short
    // heartbeat and leaves; the device times it out and latches the fault with nobody there.
    {
        let mut first = Client::connect(port(), 0x0f0f).unwrap();
        let safety = SafetyConfig { heartbeat_timeout_ticks: HEARTBEAT_TIMEOUT_US as u32 };
        first.request(Command::Configure(ConfigItem::Safety(safety))).unwrap();
    }
    std::thread::sleep(Duration::from_micros(3 * HEARTBEAT_TIMEOUT_US));
    // The next host: its fault is the earlier one's, cleared and said in words; homing goes
    // by what happens after.
    let mut heard = Heard::default();
    let mut client =
        bring_up_with(&rig_file, port(), &mut heard).unwrap_or_else(|e| panic!("{e}; {:?}", heard.0));
    assert!(
        heard.0.iter().any(|h| h.contains("latched a fault: the host went silent")),
        "the cleared fault is named: {:?}",
        heard.0
    );
    assert!(heard.0.iter().any(|h| h.starts_with("homed gantry after")), "{:?}", heard.0);
    // The fault's event is still queued for the session's journal, under the device's boot id.
    let boot = client.info().boot_id;
    let stale: Vec<_> =
        client.take_events().into_iter().filter(|e| matches!(e.event, Event::Fault { .. })).collect();
    assert_eq!(stale.len(), 1, "{stale:?}");
    assert_eq!(stale[0].boot_id, boot, "journaled under the device's boot id, not 0");
}
