//! `lightrig acquire` with a GenICam camera: Aravis's own fake GigE Vision camera
//! (`arv-fake-gv-camera-0.8`, Debian's `aravis-tools`) on 127.0.0.1, software-triggered by the
//! host at every trigger the virtual controller reports, every frame through real GigE Vision
//! packets. Built with `--features genicam` (CI does); the fake camera listens on
//! 127.0.0.1:3956 only, so these tests take turns.

#![cfg(feature = "genicam")]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use lightrig_host::session::{journal_records, Record, Session};

static ONE_CAMERA: Mutex<()> = Mutex::new(());

/// The fake camera, killed when dropped.
struct FakeCamera(Child);

impl FakeCamera {
    /// Starts it, `lost_per_mille` of its stream packets dropped on purpose; returns once it
    /// listens.
    fn start(lost_per_mille: u32) -> FakeCamera {
        let mut cmd = Command::new("arv-fake-gv-camera-0.8");
        cmd.args(["-i", "127.0.0.1"]).stdout(Stdio::null()).stderr(Stdio::null());
        if lost_per_mille > 0 {
            cmd.args(["-r", &lost_per_mille.to_string()]);
        }
        let child = cmd.spawn().expect("arv-fake-gv-camera-0.8 (Debian: apt install aravis-tools)");
        let deadline = Instant::now() + Duration::from_secs(10);
        // 127.0.0.1:3956 bound (in /proc/net/udp: local address 0100007F:0F74).
        while !std::fs::read_to_string("/proc/net/udp").unwrap_or_default().contains("0100007F:0F74") {
            assert!(Instant::now() < deadline, "the fake camera did not come up");
            std::thread::sleep(Duration::from_millis(20));
        }
        FakeCamera(child)
    }
}

impl Drop for FakeCamera {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
        // Gone from 127.0.0.1:3956 before the next one starts.
        let deadline = Instant::now() + Duration::from_secs(5);
        while std::fs::read_to_string("/proc/net/udp").unwrap_or_default().contains("0100007F:0F74")
            && Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lightrig-genicam-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn lightrig(args: &[String]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightrig")).args(args).stdin(Stdio::null()).output().unwrap()
}

/// The shipped gantry rig with its camera on the fake GenICam camera and a short reflectance
/// pass of `positions` positions (3 exposures each).
fn sets(positions: u32) -> Vec<String> {
    let to = (positions - 1) as i32;
    [
        "camera[0].source={ kind = \"genicam\", address = \"127.0.0.1\", pixel_format = \"Mono8\" }"
            .to_string(),
        format!("plan.pass_mm=[0, {to}]"),
        "plan.step_mm=1".into(),
        // The virtual controller runs in real time beside a real camera: no homing run.
        "stepper[0].homing={ mode = \"none\" }".into(),
        "plan.passes=[\"reflectance\"]".into(),
    ]
    .into_iter()
    .flat_map(|s| ["--set".to_string(), s])
    .collect()
}

fn rig() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/lls-gantry.toml").display().to_string()
}

fn acquire(session: &Path, positions: u32) -> Output {
    let mut args = vec!["acquire".into(), rig(), "--session".into(), session.display().to_string()];
    args.extend(sets(positions));
    lightrig(&args)
}

fn missing_reasons(session: &Path) -> Vec<String> {
    journal_records(session)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            Record::FrameMissing(m) => Some(m.reason),
            _ => None,
        })
        .collect()
}

#[test]
fn a_whole_acquisition_through_gige_vision() {
    let _turn = ONE_CAMERA.lock().unwrap_or_else(|e| e.into_inner());
    let camera = FakeCamera::start(0);
    let dir = scratch("whole");
    let session = dir.join("session");
    let out = acquire(&session, 6);
    let said = String::from_utf8_lossy(&out.stderr);
    let (s, _) = Session::read(&session).unwrap();
    assert!(s.is_done());
    let frames = s.frame_index();
    // 6 positions × 3 exposures, each paired with its trigger. With the receive buffer sized
    // for the payload the loopback loses about one frame in a few hundred (measured: 1 of 200
    // at 20 Hz); such a frame is named by its id, never shifts the others.
    let reasons = missing_reasons(&session);
    assert_eq!(out.status.code(), Some(if reasons.is_empty() { 0 } else { 5 }), "{said}");
    assert_eq!(frames.len() + reasons.len(), 18, "{said}");
    assert!(reasons.len() <= 1, "{reasons:?}");
    for r in &reasons {
        assert!(r.contains("the camera delivered frame id"), "{r}");
    }
    assert!(!said.contains("extra-*"), "{said}");
    for f in &frames {
        let img = lightrig_imaging::io::read(session.join(&f.file)).unwrap();
        assert_eq!((img.width, img.height), (512, 512), "the fake camera's frame");
    }
    // Each frame keeps the camera's frame id and timestamp: ids one apart per frame, times
    // increasing with the trigger ticks.
    let stamps: Vec<_> = frames.iter().map(|f| (f.frame, f.tick, f.camera_stamp.expect("stamped"))).collect();
    for w in stamps.windows(2) {
        let ((f0, t0, a), (f1, t1, b)) = (w[0], w[1]);
        assert_eq!(lightrig_genicam::ids::frames_after(a.id, b.id), Some(u64::from(f1 - f0)));
        assert!(b.time_ns > a.time_ns && t1 > t0);
    }
    // `lightrig devices` lists it beside the controllers.
    let listed = lightrig(&["devices".into(), "--genicam".into(), "127.0.0.1".into()]);
    let text = String::from_utf8_lossy(&listed.stdout);
    assert!(text.contains("genicam:127.0.0.1") && text.contains("Aravis Fake"), "{text}");
    // Gone: the address is named, the exit status says it is the device.
    drop(camera);
    let gone = lightrig(&["devices".into(), "--genicam".into(), "127.0.0.1".into()]);
    let said = String::from_utf8_lossy(&gone.stderr);
    assert_eq!(gone.status.code(), Some(3), "{said}");
    assert!(said.contains("127.0.0.1: no GenICam camera answers there"), "{said}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn frames_lost_on_the_wire_are_named_by_their_frame_id() {
    let _turn = ONE_CAMERA.lock().unwrap_or_else(|e| e.into_inner());
    // 2 of every 1000 stream packets dropped: a 256 KiB frame has ~190, so about a third of
    // the frames come back incomplete.
    let _camera = FakeCamera::start(2);
    let dir = scratch("lossy");
    let session = dir.join("session");
    let out = acquire(&session, 10);
    let said = String::from_utf8_lossy(&out.stderr);
    let (s, _) = Session::read(&session).unwrap();
    let reasons = missing_reasons(&session);
    assert!(!reasons.is_empty(), "some frames lost: {said}");
    assert_eq!(out.status.code(), Some(5), "complete, frames missing: {said}");
    assert!(said.contains("warning: step 0 (") && said.contains("--retake-missing"), "{said}");
    // A frame whose leader packet is dropped never reaches Aravis at all (about one run in
    // ten has one): its trigger is missing for want of a frame; the others are named by the
    // camera's frame id.
    let named = |r: &String| r.contains("the camera delivered frame id") && r.contains("incomplete");
    for r in &reasons {
        assert!(named(r) || r.contains("no frame arrived within the wait"), "{r}");
    }
    assert!(reasons.iter().any(named), "{reasons:?}");
    // Every trigger has its frame or a missing record naming why: none shifted, no extras.
    assert_eq!(s.frame_index().len() + reasons.len(), 30);
    // Before that the step was acquired twice more (a third of its frames lost each time), and
    // the run said so.
    let retried: Vec<String> = journal_records(&session)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            Record::StepAbandoned { reason, .. } => Some(reason),
            _ => None,
        })
        .collect();
    assert_eq!(retried.len(), 2, "{retried:?}");
    for r in &retried {
        assert!(r.starts_with("lost ") && r.contains("of 30 frames (camera 0 frame "), "{r}");
        assert!(r.ends_with("the step is acquired again"), "{r}");
    }
    assert!(said.contains("2 step attempt(s) lost frames and were acquired again"), "{said}");
    assert!(!said.contains("extra-*"), "{said}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn software_triggers_faster_than_the_camera_are_fired_one_frame_at_a_time() {
    let _turn = ONE_CAMERA.lock().unwrap_or_else(|e| e.into_inner());
    let _camera = FakeCamera::start(0);
    let dir = scratch("fast");
    let session = dir.join("session");
    // The controller triggers at 33 Hz; the fake camera reads its trigger register once per
    // 40 ms. Fired as the controller reports them, two triggers in one period made one frame
    // (25 to 45 of 120 missing, the frames after each pairing with the trigger before theirs).
    let mut args = vec!["acquire".into(), rig(), "--session".into(), session.display().to_string()];
    args.extend(sets(10));
    args.extend(["--set".into(), "camera[0].min_interval_us=30000".into()]);
    let out = lightrig(&args);
    let said = String::from_utf8_lossy(&out.stderr);
    let (s, _) = Session::read(&session).unwrap();
    let reasons = missing_reasons(&session);
    assert_eq!(out.status.code(), Some(if reasons.is_empty() { 0 } else { 5 }), "{said}");
    assert!(reasons.len() <= 1, "{reasons:?}");
    for r in &reasons {
        assert!(r.contains("the camera delivered frame id"), "only a frame lost on the wire: {r}");
    }
    assert_eq!(s.frame_index().len() + reasons.len(), 30, "{said}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_camera_stopped_mid_run_and_restarted_is_resumed_to_a_complete_session() {
    let _turn = ONE_CAMERA.lock().unwrap_or_else(|e| e.into_inner());
    let camera = FakeCamera::start(0);
    let dir = scratch("restart");
    let session = dir.join("session");
    let mut args = vec!["acquire".into(), rig(), "--session".into(), session.display().to_string()];
    args.extend(sets(40));
    let mut run = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(&args)
        .stdin(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Stop the camera a dozen triggers into the pass.
    let deadline = Instant::now() + Duration::from_secs(60);
    let triggered = || {
        journal_records(&session).map_or(0, |rs| {
            rs.iter()
                .filter(|r| {
                    matches!(r, Record::Event { event: lightrig_protocol::event::Event::Trigger(_), .. })
                })
                .count()
        })
    };
    while triggered() < 12 {
        assert!(Instant::now() < deadline && run.try_wait().unwrap().is_none(), "no triggers within 60 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(camera);
    let out = run.wait_with_output().unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "the run stops when the camera goes: {said}");
    assert!(said.contains("GenICam camera 127.0.0.1"), "{said}");
    // The camera is back (its frame counter starts afresh): resume completes the session.
    let _camera = FakeCamera::start(0);
    let mut args = vec!["resume".into(), session.display().to_string(), "--rig".into(), rig()];
    args.extend(sets(40));
    let out = lightrig(&args);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{said}");
    let (s, _) = Session::read(&session).unwrap();
    assert!(s.is_done());
    assert_eq!(s.frame_index().len(), 120, "every trigger paired once: {said}");
    assert!(s.verify().is_empty());
    std::fs::remove_dir_all(&dir).ok();
}
