//! The acquisition engine end to end on the virtual device: one frame per trigger in the
//! session, missing and duplicate frames recorded, link damage, an unplug, and a host killed
//! at many points, each resumed to a complete session.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use lightrig_firmware::sim::virtual_device_info;
use lightrig_firmware::sim::SimBoard;
use lightrig_host::acquire::{self, plan_summary, AcquireError, Captured, DirectoryInput, FrameInput};
use lightrig_host::client::Client;
use lightrig_host::plan::{lls, Plan};
use lightrig_host::session::{Manifest, Record, Session};
use lightrig_protocol::event::TriggerEvent;
use lightrig_sim::transport::{Impairment, VirtualTransport};

/// A camera for tests: on every trigger it makes a small frame that names the trigger (so a
/// test can check each stored frame belongs to its trigger), and it can drop or duplicate
/// frames, or kill the whole process at a given trigger (a host crash).
#[derive(Default)]
struct TestCamera {
    triggers: u64,
    ready: Vec<Captured>,
    drop: Vec<u64>,
    duplicate: Vec<u64>,
    crash_at: Option<u64>,
}

impl FrameInput for TestCamera {
    fn begin_step(&mut self, _step: &lightrig_host::plan::Step) -> std::io::Result<()> {
        Ok(())
    }

    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        let n = self.triggers;
        self.triggers += 1;
        if self.crash_at == Some(n) {
            std::process::abort();
        }
        let data = format!(
            "seq {} item {} frame {} tick {} x {}\n",
            t.sequence, t.item, t.frame, t.tick, t.snapshot.axes[0]
        );
        let c = Captured {
            camera: t.camera,
            frame: Some(t.frame),
            ext: "txt".into(),
            data: data.into_bytes(),
            host_us: host_us.unwrap_or(0.0) + 500.0,
            before_step: false,
            stamp: None,
        };
        if self.duplicate.contains(&n) {
            self.ready.push(c.clone());
        }
        if !self.drop.contains(&n) {
            self.ready.push(c);
        }
        Ok(())
    }

    fn poll(&mut self, _now: f64) -> std::io::Result<Vec<Captured>> {
        Ok(std::mem::take(&mut self.ready))
    }
}

/// A camera whose own software writes one numbered file per trigger into a directory (the
/// same text as [`TestCamera`]'s frames), read back through the host's [`DirectoryInput`], as
/// a real camera's frames are.
struct FileCamera {
    dir: PathBuf,
    next: u64,
    input: DirectoryInput,
}

impl FileCamera {
    fn new(dir: &Path) -> Self {
        let input = DirectoryInput::new(0, dir, "img_{frame:06}.txt").unwrap();
        FileCamera { dir: dir.to_path_buf(), next: 0, input }
    }

    fn write(&mut self, text: &str) -> PathBuf {
        let path = self.dir.join(format!("img_{:06}.txt", self.next));
        self.next += 1;
        std::fs::write(&path, text).unwrap();
        path
    }
}

impl FrameInput for FileCamera {
    fn begin_step(&mut self, step: &lightrig_host::plan::Step) -> std::io::Result<()> {
        self.input.begin_step(step)
    }

    fn on_trigger(&mut self, t: &TriggerEvent, _host_us: Option<f64>) -> std::io::Result<()> {
        let x = t.snapshot.axes[0];
        self.write(&format!("seq {} item {} frame {} tick {} x {x}\n", t.sequence, t.item, t.frame, t.tick));
        Ok(())
    }

    fn poll(&mut self, now: f64) -> std::io::Result<Vec<Captured>> {
        self.input.poll(now)
    }
}

fn lls_plan() -> Plan {
    lls::plan(&common::lls_params()).unwrap()
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lightrig-acq-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn new_session(dir: &Path, plan: &Plan) -> Session {
    Session::create(dir, Manifest::new("# test rig", &virtual_device_info(), plan_summary(plan))).unwrap()
}

fn connect(board: SimBoard) -> Client<VirtualTransport> {
    common::setup(Client::connect(VirtualTransport::new(virtual_device_info(), board), 5).unwrap())
}

/// Every planned trigger has exactly one frame in its step's completed attempt, and that frame
/// is the one its trigger made (the right gantry position).
fn check_complete(dir: &Path, plan: &Plan) {
    let (s, _) = Session::read(dir).unwrap();
    assert!(s.is_done(), "session done");
    assert_eq!(s.verify(), vec![], "every file intact");
    for step in &plan.steps {
        let frames = s.frames_of(step.id);
        let by_frame: BTreeMap<u32, _> = frames.iter().map(|f| (f.frame, f)).collect();
        assert_eq!(by_frame.len(), frames.len(), "no frame twice in step {}", step.id);
        assert_eq!(frames.len(), step.shot_count(), "step {}", step.id);
        for (k, f) in &by_frame {
            let text = std::fs::read_to_string(dir.join(&f.file)).unwrap();
            let x = -800 + 80 * *k as i64;
            assert!(text.starts_with(&format!("seq {} ", f.sequence)), "{text}");
            assert!(text.ends_with(&format!("x {x}\n")), "frame {k} of step {}: {text}", step.id);
        }
    }
}

#[test]
fn a_run_stores_one_frame_per_trigger_and_records_missing_and_duplicate_frames() {
    let dir = temp_dir("basic");
    // No step acquired again for its lost frame: the frame is recorded missing.
    let plan = Plan { lost_retries: 0, ..lls_plan() };
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    let mut cam = TestCamera { drop: vec![5], duplicate: vec![30], ..Default::default() };
    let (mut updates, mut warned, mut counts) = (Vec::new(), Vec::new(), Vec::new());
    acquire::run(&mut client, &mut session, &plan, &mut cam, |p| {
        updates.push((p.steps_done, p.triggered, p.to_trigger));
        counts.push((p.frames, p.received, p.bytes, p.planned_done_us, p.planned_left_us));
        warned.extend(p.missing_now.map(|w| (p.steps_done, p.missing, w)));
    })
    .unwrap();
    // The lost frame is said as its step is stored, with its camera, frame and why.
    assert_eq!(warned.len(), 1, "{warned:?}");
    let (steps_done, missing, what) = &warned[0];
    assert_eq!((*steps_done, *missing), (1, 1));
    assert!(
        what.starts_with("step 0 (") && what.contains("1 of 21 frames missing (camera 0 frame 5: "),
        "{what}"
    );
    // Progress at every trigger within a step (21 each), as the step's frames arrive after its
    // sequence (this camera gives them all at the first look), then at the step's end.
    let ends: Vec<usize> = updates.windows(2).filter(|w| w[1].0 > w[0].0).map(|w| w[1].0).collect();
    assert_eq!(ends, [1, 2, 3]);
    assert_eq!(updates.len(), 3 * (21 + 2));
    assert!(updates.iter().all(|u| u.2 == 63));
    assert_eq!(
        updates[..21].iter().map(|u| (u.0, u.1)).collect::<Vec<_>>(),
        (1..=21).map(|t| (0, t)).collect::<Vec<_>>()
    );
    assert_eq!((updates[21], updates[22]), ((0, 21, 63), (1, 21, 63)));
    assert_eq!(updates.last(), Some(&(3, 63, 63)));
    // Frames are counted as they arrive (step 0: 20 of 21 and the duplicate of frame 30 is
    // step 1's), stored at the step's end with their bytes; the plan's time moves from left to
    // done a step's share at each trigger.
    let file_bytes = |step: u32| -> u64 { session.frames_of(step).iter().map(|f| f.bytes).sum() };
    let bytes: Vec<u64> = (0..3).map(file_bytes).collect();
    let step_us: Vec<u64> =
        plan.steps.iter().map(|s| s.min_ticks * 1_000_000 / u64::from(plan.tick_hz)).collect();
    let all_us: u64 = step_us.iter().sum();
    assert_eq!(counts[0], (0, 0, 0, step_us[0] / 21, all_us - step_us[0] / 21));
    assert_eq!(counts[21], (0, 20, 0, step_us[0], all_us - step_us[0]));
    assert_eq!(counts[22], (20, 0, bytes[0], step_us[0], all_us - step_us[0]));
    assert_eq!(counts[23 + 22], (20 + 21, 0, bytes[0] + bytes[1], step_us[0] + step_us[1], step_us[2]));
    assert_eq!(counts.last(), Some(&(62, 0, bytes.iter().sum(), all_us, 0)));
    assert!(counts.windows(2).all(|w| w[1].3 >= w[0].3 && w[1].3 + w[1].4 == all_us));
    assert!(session.is_done());
    let frames: usize = plan.steps.iter().map(|s| session.frames_of(s.id).len()).sum();
    assert_eq!(frames, 62, "63 triggers, one frame lost");
    let st = session.state();
    let attempts: Vec<_> = st.steps.values().flat_map(|a| a.values()).collect();
    assert_eq!(attempts.iter().map(|a| a.missing.len()).sum::<usize>(), 1);
    assert_eq!(attempts.iter().map(|a| a.extra.len()).sum::<usize>(), 1);
    assert_eq!(session.verify(), vec![]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The reasons of the abandoned attempts of `step`, in order.
fn abandoned(session: &Session, step: u32) -> Vec<String> {
    let st = session.state();
    st.steps[&step]
        .values()
        .filter_map(|a| match &a.outcome {
            lightrig_host::session::Outcome::Abandoned { reason } => Some(reason.clone()),
            _ => None,
        })
        .collect()
}

#[test]
fn a_step_that_lost_a_frame_is_acquired_again_at_once() {
    let dir = temp_dir("lost-once");
    let plan = lls_plan();
    assert_eq!(plan.lost_retries, 2);
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // The camera misses the 6th trigger of the run (step 0's frame 5), once.
    let mut cam = TestCamera { drop: vec![5], ..Default::default() };
    let mut updates = Vec::new();
    acquire::run(&mut client, &mut session, &plan, &mut cam, |p| {
        // Reports of frames arriving after the sequence leave the triggers as they were.
        if p.received == 0 || updates.last() != Some(&(p.steps_done, p.triggered)) {
            updates.push((p.steps_done, p.triggered))
        }
    })
    .unwrap();
    assert_eq!(cam.triggers, 63 + 21, "step 0 fired twice");
    assert_eq!(
        abandoned(&session, 0),
        ["lost 1 of 21 frames (camera 0 frame 5: no frame arrived within the wait): the step is acquired again"]
    );
    assert!(abandoned(&session, 1).is_empty() && abandoned(&session, 2).is_empty());
    // The second attempt counts its triggers from the step's start again.
    assert_eq!(updates[21], (0, 1), "{updates:?}");
    assert_eq!(updates.last(), Some(&(3, 63)));
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_frame_lost_at_every_try_is_recorded_missing_and_a_silent_camera_is_not_retried() {
    let dir = temp_dir("lost-always");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // Step 0's frame 5 lost in each of its three attempts (triggers 5, 26, 47 of the run).
    let mut cam = TestCamera { drop: vec![5, 26, 47], ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    assert_eq!(cam.triggers, 63 + 2 * 21);
    assert_eq!(abandoned(&session, 0).len(), 2);
    assert_eq!(session.frames_of(0).len(), 20);
    let missing = session.state().missing_of(0);
    assert_eq!(missing.len(), 1);
    assert_eq!((missing[0].frame, missing[0].reason.as_str()), (5, "no frame arrived within the wait"));
    assert_eq!(session.frames_of(1).len() + session.frames_of(2).len(), 42);
    std::fs::remove_dir_all(&dir).unwrap();

    // A camera that delivers nothing is not unlucky: every trigger missing, no second try.
    let dir = temp_dir("silent");
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    let mut cam = TestCamera { drop: (0..63).collect(), ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    assert_eq!(cam.triggers, 63);
    assert!((0..3).all(|s| abandoned(&session, s).is_empty() && session.state().missing_of(s).len() == 21));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A line-triggered camera that stamps each frame by its own clock (1 µs per tick, 5 s
/// ahead) and numbers frames by its own counter from each step's start; it misses the
/// triggers at the run's indices in `miss` (busy: no frame, its counter stays).
#[derive(Default)]
struct StampingCamera {
    triggers: u64,
    counter: u32,
    miss: Vec<u64>,
    ready: Vec<Captured>,
}

impl FrameInput for StampingCamera {
    fn begin_step(&mut self, _step: &lightrig_host::plan::Step) -> std::io::Result<()> {
        self.counter = 0;
        Ok(())
    }

    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        let n = self.triggers;
        self.triggers += 1;
        if self.miss.contains(&n) {
            return Ok(());
        }
        let data = format!(
            "seq {} item {} frame {} tick {} x {}\n",
            t.sequence, t.item, t.frame, t.tick, t.snapshot.axes[0]
        );
        let id = u64::from(self.counter);
        self.ready.push(Captured {
            camera: t.camera,
            frame: Some(self.counter),
            ext: "txt".into(),
            data: data.into_bytes(),
            host_us: host_us.unwrap_or(0.0) + 500.0,
            before_step: false,
            stamp: Some(lightrig_host::session::CameraStamp { id, time_ns: 5_000_000_000 + t.tick * 1000 }),
        });
        self.counter += 1;
        Ok(())
    }

    fn poll(&mut self, _now: f64) -> std::io::Result<Vec<Captured>> {
        Ok(std::mem::take(&mut self.ready))
    }

    fn stamps_follow_triggers(&self) -> bool {
        true
    }
}

#[test]
fn a_trigger_the_camera_missed_is_found_by_its_stamps_and_the_step_acquired_again() {
    let dir = temp_dir("missed");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // The camera misses step 0's trigger 12: frames 12-19 come numbered one early.
    let mut cam = StampingCamera { miss: vec![12], ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    let reasons = abandoned(&session, 0);
    assert_eq!(reasons.len(), 1, "{reasons:?}");
    assert!(
        reasons[0].starts_with("lost the pairing of camera 0: 8 frames off their triggers' ticks by the camera's clock, from frame 12 (+"),
        "{}",
        reasons[0]
    );
    drop(session);
    // Acquired again: every stored frame is its own trigger's.
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_trigger_missed_at_every_try_is_recorded_missing_and_the_frames_paired_by_their_stamps() {
    let dir = temp_dir("missed-always");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // Step 0's trigger 12 missed in each of its three attempts.
    let mut cam = StampingCamera { miss: vec![12, 12 + 21, 12 + 42], ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    assert_eq!(abandoned(&session, 0).len(), 2);
    let missing = session.state().missing_of(0);
    assert_eq!(missing.len(), 1);
    assert_eq!(missing[0].frame, 12);
    assert!(missing[0].reason.contains("the camera missed this trigger"), "{}", missing[0].reason);
    assert!(session.state().extra_of(0).is_empty());
    // Every stored frame is its own trigger's (the gantry position it names).
    let frames = session.frames_of(0);
    assert_eq!(frames.len(), 20);
    for f in &frames {
        let text = std::fs::read_to_string(dir.join(&f.file)).unwrap();
        assert!(text.contains(&format!(" frame {} ", f.frame)), "frame {}: {text}", f.frame);
        assert!(
            text.ends_with(&format!("x {}\n", -800 + 80 * i64::from(f.frame))),
            "frame {}: {text}",
            f.frame
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn link_damage_costs_retransmissions_not_frames() {
    let dir = temp_dir("damage");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    client.transport_mut().impair(Impairment {
        drop_ppm: 3000,
        corrupt_ppm: 3000,
        duplicate_ppm: 3000,
        seed: 42,
    });
    acquire::run(&mut client, &mut session, &plan, &mut TestCamera::default(), |_| {}).unwrap();
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_unplug_mid_step_abandons_it_and_resume_completes_the_session() {
    let dir = temp_dir("unplug");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // Pull the cable 0.4 s (simulated) into the run: in the middle of a pass.
    let now = lightrig_host::transport::Transport::now_us(client.transport());
    client.transport_mut().unplug_at(now + 400_000);
    let mut cam = TestCamera::default();
    let err = acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap_err();
    assert!(matches!(err, AcquireError::Device(_)), "{err}");
    assert!(err.to_string().contains("`lightrig resume` acquires it again"), "{err}");
    let interrupted = plan.steps.iter().find(|s| !session.steps_done().contains(&s.id)).unwrap().id;
    assert_eq!(session.open_attempt(), None, "the interrupted attempt was abandoned, not left open");
    // Plug back in: the device kept its configuration and is still running the old sequence.
    let mut transport = client.into_transport();
    transport.replug();
    let mut client = Client::connect(transport, 6).unwrap();
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    let attempts = session.state().steps[&interrupted].len();
    assert_eq!(attempts, 2, "the interrupted pass took two attempts");
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_straggler_of_a_cut_short_attempt_is_kept_as_an_extra_and_shifts_no_pairing() {
    use lightrig_host::session::ExtraReason;
    let dir = temp_dir("straggler");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    let now = lightrig_host::transport::Transport::now_us(client.transport());
    client.transport_mut().unplug_at(now + 400_000);
    let mut cam = FileCamera::new(&dir.join("camera"));
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap_err();
    let interrupted = plan.steps.iter().find(|s| !session.steps_done().contains(&s.id)).unwrap().id;
    // The camera was still reading out the last exposure of the cut-short attempt: its file
    // lands after the host gave up on the step, dated when the exposure was made.
    let number = cam.next as u32;
    let straggler = cam.write("straggler\n");
    let then = std::time::SystemTime::now() - std::time::Duration::from_secs(1);
    std::fs::File::options().write(true).open(&straggler).unwrap().set_modified(then).unwrap();
    let mut transport = client.into_transport();
    transport.replug();
    let mut client = Client::connect(transport, 6).unwrap();
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    // Every frame is its own trigger's (check_complete reads each one's gantry position), and
    // the straggler is kept, named for what it is.
    let (_, attempt) = session.state().done_attempt(interrupted).unwrap();
    // The cut-short attempt's frames that were never collected are kept the same way.
    let extra: Vec<_> = attempt.extra.iter().map(|x| (x.reason, x.frame)).collect();
    assert_eq!(extra, (0..=number).map(|n| (ExtraReason::BeforeStep, n)).collect::<Vec<_>>());
    let kept = std::fs::read_to_string(dir.join(&attempt.extra[number as usize].file)).unwrap();
    assert_eq!(kept, "straggler\n");
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_run_rides_out_an_unplug_by_reconnecting_and_stores_every_frame_once() {
    use lightrig_host::client::ClientError;
    use lightrig_host::transport::Transport;
    let dir = temp_dir("reconnect");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    let now = client.transport().now_us();
    client.transport_mut().unplug_at(now + 400_000);
    let mut cam = TestCamera::default();
    // The cable stays out through the first reconnection attempt; the second finds it back.
    let mut stash: Option<VirtualTransport> = None;
    let mut tries = Vec::new();
    let mut reconnect = |old: Option<VirtualTransport>, k: u32| {
        tries.push((k, old.is_some()));
        if let Some(t) = old {
            stash = Some(t);
        }
        if k == 1 {
            return Err(ClientError::Timeout {
                device: "virtual".into(),
                what: "Hello".into(),
                waited_ms: 1,
            });
        }
        let mut t = stash.take().expect("the transport handed over at the first attempt");
        t.replug();
        Client::connect(t, 7)
    };
    let mut said = Vec::new();
    acquire::run_reconnecting(
        client,
        &mut reconnect,
        5,
        &mut session,
        &plan,
        &mut cam,
        &mut acquire::Unattended("virtual"),
        |_| {},
        |m| said.push(m.to_string()),
    )
    .unwrap();
    assert_eq!(tries, [(1, true), (2, false)]);
    assert!(said[0].starts_with("device lost: "), "{said:?}");
    assert!(said[1].starts_with("reconnection 1/5 failed: "), "{said:?}");
    assert_eq!(said.len(), 3, "{said:?}");
    let interrupted: Vec<_> =
        session.state().steps.iter().filter(|(_, a)| a.len() == 2).map(|(s, _)| *s).collect();
    assert_eq!(interrupted.len(), 1, "one step was interrupted and acquired again");
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn only_a_lost_link_is_worth_reconnecting_for() {
    use lightrig_host::client::ClientError;
    use lightrig_protocol::event::FaultCause;
    let fault = |cause| ClientError::Fault { device: "d".into(), cause, tick: 1 };
    assert!(acquire::is_link_loss(&fault(FaultCause::HeartbeatLost)));
    assert!(!acquire::is_link_loss(&fault(FaultCause::TriggerTooSoon { camera: 0 })));
    let io = ClientError::Io { device: "d".into(), error: std::io::Error::other("unplugged") };
    assert!(acquire::is_link_loss(&io));
}

/// Child side of the kill test: runs the acquisition into `LIGHTRIG_ACQ_DIR` and aborts the
/// process at trigger `LIGHTRIG_ACQ_CRASH` (as a host crash would).
#[test]
fn acquisition_child() {
    let (Ok(dir), Ok(crash)) = (std::env::var("LIGHTRIG_ACQ_DIR"), std::env::var("LIGHTRIG_ACQ_CRASH"))
    else {
        return;
    };
    let plan = lls_plan();
    let dir = PathBuf::from(dir);
    let mut session = match Session::open(&dir) {
        Ok((s, _)) => s,
        Err(_) => new_session(&dir, &plan),
    };
    let mut client = connect(SimBoard::default());
    let mut cam = TestCamera { crash_at: Some(crash.parse().unwrap()), ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
}

#[test]
fn a_host_killed_at_any_point_resumes_to_a_complete_session() {
    let plan = lls_plan();
    let exe = std::env::current_exe().unwrap();
    // Crash points spread over the run: early, at step boundaries, mid-step; two crashes in a
    // row for one session.
    for (case, crashes) in
        [vec![0u64], vec![20], vec![21], vec![22], vec![40, 10], vec![62]].into_iter().enumerate()
    {
        let dir = temp_dir(&format!("kill{case}"));
        for &crash in &crashes {
            let status = std::process::Command::new(&exe)
                .args(["--exact", "acquisition_child", "--nocapture", "--test-threads=1"])
                .env("LIGHTRIG_ACQ_DIR", &dir)
                .env("LIGHTRIG_ACQ_CRASH", crash.to_string())
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .status()
                .unwrap();
            assert!(!status.success(), "the child crashed at trigger {crash}");
        }
        // Resume in this process with a new device connection.
        let (mut session, _recovery) = Session::open(&dir).unwrap();
        let done_before = session.steps_done().len();
        let mut client = connect(SimBoard::default());
        acquire::run(&mut client, &mut session, &plan, &mut TestCamera::default(), |_| {}).unwrap();
        drop(session);
        check_complete(&dir, &plan);
        assert!(done_before < plan.steps.len(), "case {case}: the crash came before the end");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn an_interlock_fault_is_cleared_only_on_a_persons_word() {
    use lightrig_host::acquire::{needs_a_person, recover, Recovered};
    use lightrig_host::client::ClientError;
    use lightrig_protocol::event::{DeviceState, FaultCause};
    use lightrig_protocol::sequence::Action;
    use lightrig_protocol::{Command, Reply};
    // Laser 0 on the interlock loop (closed: high), armed and on; then the loop opens.
    use lightrig_protocol::config::{ConfigItem, Input, LaserConfig, Polarity};
    let mut c = connect(SimBoard::default());
    let on_the_loop = LaserConfig {
        channel: 0,
        wavelength_nm: 635,
        warmup_ticks: 0,
        max_on_ticks: 600_000_000,
        enable: Polarity::ActiveHigh,
        interlock: Input::Wired(Polarity::ActiveHigh),
    };
    c.request(Command::Configure(ConfigItem::Laser(on_the_loop))).unwrap();
    c.request(Command::Arm { lasers: 1 }).unwrap();
    c.request(Command::Immediate(Action::Laser { channel: 0, on: true })).unwrap();
    c.transport_mut().device_mut().rig_mut().board_mut().interlocks[0] = false;
    c.idle(1_000).unwrap();
    let faulted = || DeviceState::Faulted(FaultCause::Interlock { channel: 0 });
    let state = |c: &mut Client<VirtualTransport>| match c.request(Command::GetStatus).unwrap() {
        Reply::Status(s) => s.state,
        other => panic!("{other:?}"),
    };
    assert_eq!(state(&mut c), faulted());
    // Without a person's word the fault stays latched, and the error says what to do.
    let e = recover(&mut c, &mut |cause: &FaultCause| !needs_a_person(cause)).unwrap_err();
    assert!(matches!(e, ClientError::NeedsConfirmation { cause: FaultCause::Interlock { channel: 0 }, .. }));
    let words = e.to_string();
    assert!(words.contains("laser 0's interlock opened") && words.contains("confirm"), "{words}");
    assert_eq!(state(&mut c), faulted());
    // With it (the interlock closed again, the person said so), it is cleared and reported.
    c.transport_mut().device_mut().rig_mut().board_mut().interlocks[0] = true;
    let found = recover(&mut c, &mut |_: &FaultCause| true).unwrap();
    assert_eq!(found, Recovered { aborted: None, cleared: Some(FaultCause::Interlock { channel: 0 }) });
    assert_eq!(state(&mut c), DeviceState::Ready);
}

/// [`TestCamera`] that asks for a stop (as Ctrl-C does) at trigger `at`.
struct StopAt {
    cam: TestCamera,
    at: u64,
    interrupt: std::sync::Arc<lightrig_host::client::Interrupt>,
}

impl FrameInput for StopAt {
    fn begin_step(&mut self, step: &lightrig_host::plan::Step) -> std::io::Result<()> {
        self.cam.begin_step(step)
    }
    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        if self.cam.triggers == self.at {
            self.interrupt.request();
        }
        self.cam.on_trigger(t, host_us)
    }
    fn poll(&mut self, now: f64) -> std::io::Result<Vec<Captured>> {
        self.cam.poll(now)
    }
}

#[test]
fn ctrl_c_stops_the_device_at_once_leaves_it_disarmed_and_resume_completes_the_session() {
    use lightrig_host::client::{ClientError, Interrupt};
    use lightrig_protocol::event::{DeviceState, FaultCause};
    use lightrig_protocol::{Command, Reply};
    let dir = temp_dir("ctrl-c");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    let interrupt = std::sync::Arc::new(Interrupt::default());
    client.set_interrupt(interrupt.clone());
    // Ctrl-C at the 30th trigger, in the middle of the second pass, its lasers on.
    let mut cam = StopAt { cam: TestCamera::default(), at: 30, interrupt: interrupt.clone() };
    let err = acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap_err();
    assert!(matches!(err, AcquireError::Device(ClientError::Interrupted { .. })), "{err}");
    assert!(interrupt.stopped());
    assert!(err.to_string().contains("EmergencyStop"), "{err}");
    assert_eq!(session.open_attempt(), None, "the interrupted attempt was abandoned");
    // The stop is final for whoever holds the interrupt: nothing more goes through.
    let again = client.request(Command::ClearFault).unwrap_err();
    assert!(matches!(again, ClientError::Interrupted { answered: true, .. }), "{again}");
    // A new interrupt: a new process (`lightrig resume`).
    client.set_interrupt(std::sync::Arc::new(Interrupt::default()));
    let Reply::Status(s) = client.request(Command::GetStatus).unwrap() else { panic!("no status") };
    assert_eq!(s.state, DeviceState::Faulted(FaultCause::EmergencyStop));
    assert_eq!((s.armed, s.lasers_on), (0, 0), "lasers off and disarmed");
    // The stop is not cleared without a person's word, and the run does not start.
    let refused = acquire::run(&mut client, &mut session, &plan, &mut cam.cam, |_| {}).unwrap_err();
    let AcquireError::Device(e @ ClientError::NeedsConfirmation { cause: FaultCause::EmergencyStop, .. }) =
        refused
    else {
        panic!("{refused}")
    };
    assert!(e.to_string().contains("--clear-stop"), "{e}");
    let Reply::Status(s) = client.request(Command::GetStatus).unwrap() else { panic!("no status") };
    assert_eq!(s.state, DeviceState::Faulted(FaultCause::EmergencyStop), "still stopped");
    // A person said yes (bring-up's question): cleared; the session completes.
    acquire::recover(&mut client, &mut |_: &FaultCause| true).unwrap();
    acquire::run(&mut client, &mut session, &plan, &mut cam.cam, |_| {}).unwrap();
    drop(session);
    check_complete(&dir, &plan);
    // The fault it cleared is in the journal, with who cleared it.
    let cleared: Vec<_> = lightrig_host::session::journal_records(&dir)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            lightrig_host::session::Record::FaultCleared { cause, by, .. } => Some((cause, by)),
            _ => None,
        })
        .collect();
    assert_eq!(cleared, [(FaultCause::EmergencyStop, "confirmed".to_string())]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A transport whose wait on the device fails once a stop is asked for, as a serial port's
/// poll(2) does when Ctrl-C's signal lands on the thread waiting in it (EINTR).
struct BrokenBySignal {
    inner: VirtualTransport,
    interrupt: std::sync::Arc<lightrig_host::client::Interrupt>,
    failed: bool,
}

impl lightrig_host::transport::Transport for BrokenBySignal {
    fn send(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.inner.send(bytes)
    }
    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> std::io::Result<usize> {
        if self.interrupt.requested() && !self.failed {
            self.failed = true;
            return Err(std::io::ErrorKind::Interrupted.into());
        }
        self.inner.recv(buf, deadline)
    }
    fn now_us(&self) -> u64 {
        self.inner.now_us()
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn runs_alone(&self) -> bool {
        self.inner.runs_alone()
    }
}

/// The defect: Ctrl-C's signal broke the wait on the port, the run took that for a lost
/// device, reconnected, cleared its own stop and fired the lasers again. A stop asked for ends
/// the run whatever error it meets: no reconnection, the stop sent and answered.
#[test]
fn a_stop_whose_signal_breaks_the_link_is_no_lost_device_and_nothing_reconnects() {
    use lightrig_host::client::{ClientError, Interrupt};
    let dir = temp_dir("ctrl-c-eintr");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let interrupt = std::sync::Arc::new(Interrupt::default());
    let board = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    let transport = BrokenBySignal { inner: board, interrupt: interrupt.clone(), failed: false };
    let mut client = common::setup(Client::connect(transport, 5).unwrap());
    client.set_interrupt(interrupt.clone());
    let mut cam = StopAt { cam: TestCamera::default(), at: 30, interrupt: interrupt.clone() };
    let mut tries = 0;
    let mut reconnect = |_: Option<BrokenBySignal>, _: u32| -> Result<Client<BrokenBySignal>, ClientError> {
        tries += 1;
        Err(ClientError::Timeout { device: "virtual".into(), what: "Hello".into(), waited_ms: 1 })
    };
    let mut said = Vec::new();
    let err = acquire::run_reconnecting(
        client,
        &mut reconnect,
        5,
        &mut session,
        &plan,
        &mut cam,
        &mut acquire::Unattended("virtual"),
        |_| {},
        |m| said.push(m.to_string()),
    )
    .unwrap_err();
    assert!(matches!(err, AcquireError::Device(ClientError::Interrupted { answered: true, .. })), "{err}");
    assert_eq!(tries, 0, "no reconnection: {said:?}");
    assert!(said.is_empty(), "{said:?}");
    assert!(interrupt.answered(), "the device answered the stop");
    drop(session);
    let records = lightrig_host::session::journal_records(&dir).unwrap();
    assert!(!records.iter().any(|r| matches!(r, Record::FaultCleared { .. })));
    let started = records.iter().filter(|r| matches!(r, Record::StepStarted { .. })).count();
    let abandoned = records.iter().filter(|r| matches!(r, Record::StepAbandoned { .. })).count();
    assert_eq!((started, abandoned), (2, 1), "the second pass, interrupted, is not run again");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_device_reset_mid_step_is_seen_and_the_step_acquired_again_under_the_new_boot() {
    use lightrig_host::session::{journal_records, Record};
    let dir = temp_dir("reset");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // The device resets 0.4 s (simulated) into the run, in the middle of a pass, the link open.
    let now = lightrig_host::transport::Transport::now_us(client.transport());
    client.transport_mut().reset_at(now + 400_000);
    let first_boot = client.info().boot_id;
    let mut cam = TestCamera::default();
    let mut said = Vec::new();
    // Reconnecting over the same port: Hello, then configure and home again (what bring-up does).
    let mut reconnect = |old: Option<VirtualTransport>, _k: u32| {
        Ok(common::setup(Client::connect(old.expect("the port, still open"), 8)?))
    };
    acquire::run_reconnecting(
        client,
        &mut reconnect,
        1,
        &mut session,
        &plan,
        &mut cam,
        &mut acquire::Unattended("virtual"),
        |_| {},
        |m| said.push(m.to_string()),
    )
    .unwrap();
    assert!(said[0].contains("no longer knows this host's session"), "{said:?}");
    let boots: Vec<u32> = journal_records(&dir)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            Record::DeviceConnected { boot_id, .. } => Some(boot_id),
            _ => None,
        })
        .collect();
    assert_eq!(boots.len(), 2, "connected twice: {boots:?}");
    assert_eq!(boots[0], first_boot);
    assert_ne!(boots[1], first_boot, "the second connection is to the new boot");
    let interrupted: Vec<_> =
        session.state().steps.iter().filter(|(_, a)| a.len() == 2).map(|(s, _)| *s).collect();
    assert_eq!(interrupted.len(), 1, "one step was cut short and acquired again");
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_stale_hosts_sync_mid_step_costs_neither_the_session_nor_the_step() {
    use lightrig_host::session::journal_records;
    use lightrig_protocol::link::{self, FrameKind, Header};
    let dir = temp_dir("stale-sync");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // 0.4 s (simulated) into the run, in the middle of a pass, a copy of an earlier host run's
    // Sync (another nonce) of the current epoch reaches the device, as a reordering wire may
    // deliver it (§4.6.1).
    let mut out = [0u8; lightrig_protocol::MAX_FRAME];
    let epoch = client.transport().device().link().epoch();
    let h = Header { kind: FrameKind::Sync, epoch, seq: 0, ack: 0 };
    let n = link::write(&h, Some(&0x0bad_5eed_u32), &mut out);
    let now = lightrig_host::transport::Transport::now_us(client.transport());
    client.transport_mut().inject_at(now + 400_000, &out[..n]);
    let syncs = client.transport().device().link().stats().syncs;
    let mut cam = TestCamera::default();
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap_or_else(|e| panic!("{e}"));
    // It arrived, and the link went through a new epoch ...
    assert_eq!(client.transport().device().link().stats().syncs, syncs + 2);
    assert_eq!(client.transport().device().link().epoch(), epoch + 1);
    // ... and nothing else happened: one device connection, no step attempted twice, no fault.
    let records = journal_records(&dir).unwrap();
    let connected = records.iter().filter(|r| matches!(r, Record::DeviceConnected { .. })).count();
    assert_eq!(connected, 1);
    let faults: Vec<_> = records
        .iter()
        .filter(|r| matches!(r, Record::Event { event: lightrig_protocol::Event::Fault { .. }, .. }))
        .collect();
    assert_eq!(faults, Vec::<&Record>::new());
    assert!(session.state().steps.values().all(|a| a.len() == 1), "a step was acquired again");
    drop(session);
    check_complete(&dir, &plan);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_finished_sessions_missing_frames_are_retaken_by_reopening_their_steps() {
    let dir = temp_dir("retake");
    let plan = lls_plan();
    let mut session = new_session(&dir, &plan);
    let mut client = connect(SimBoard::default());
    // Step 0's frame 5 lost at each of its three tries: the session ends with it missing.
    let mut cam = TestCamera { drop: vec![5, 26, 47], ..Default::default() };
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    assert!(session.is_done());
    let missing = session.steps_missing_frames();
    assert_eq!(missing.len(), 1);
    assert_eq!(missing[0].0, 0);
    assert!(missing[0].1.starts_with("1 frame(s) missing (camera 0 frame 5: "), "{}", missing[0].1);
    drop(session);

    // Later, the camera fixed: the session is opened again and the step taken back.
    let (mut session, _) = Session::open(&dir).unwrap();
    assert!(session.is_done());
    // Only the completed attempt of a done step can be taken back.
    let wrong = Record::StepReopened { step: 0, attempt: 1, reason: "x".into(), host_time: String::new() };
    assert!(session.append(&wrong).unwrap_err().to_string().contains("its completed attempt is 3"));
    assert_eq!(session.reopen_missing().unwrap(), vec![0]);
    assert!(!session.is_done());
    assert_eq!(session.manifest().format, lightrig_host::session::FORMAT_VERSION);
    let mut client = connect(SimBoard::default());
    let mut cam = TestCamera::default();
    acquire::run(&mut client, &mut session, &plan, &mut cam, |_| {}).unwrap();
    assert_eq!(cam.triggers, 21, "only step 0 acquired again");
    drop(session);

    check_complete(&dir, &plan);
    let (s, _) = Session::read(&dir).unwrap();
    assert_eq!(s.state().done_attempt(0).map(|(a, _)| a), Some(4));
    assert!(s.state().superseded().contains(&(0, 3)), "the earlier attempt is kept, superseded");
    assert!(s.steps_missing_frames().is_empty());
    assert_eq!(s.state().done_attempt(1).map(|(a, _)| a), Some(1), "other steps untouched");
    let (mut session, _) = Session::open(&dir).unwrap();
    assert_eq!(session.reopen_missing().unwrap(), Vec::<u32>::new(), "nothing left to retake");
    assert!(session.is_done());
    std::fs::remove_dir_all(&dir).unwrap();
}
