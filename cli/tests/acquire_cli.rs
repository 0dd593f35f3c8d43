//! `lightrig acquire` end to end on example rig files in `docs/rigs/`, as a newcomer runs
//! it: `connect = "virtual"` and `source = { kind = "virtual" }`, each plan cut down to a few
//! frames (every shipped file acquired and fitted: `shipped_rigs.rs`). Every session must complete with one frame per trigger; the DISCO frames must show
//! the laser spot where the trigger's galvo codes pointed; steps that ask for a person or a
//! host instrument are journaled, refused without a terminal, and taken as done with `--yes`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use lightrig_host::session::{journal_records, trigger_events, Record, Session};

mod common;
use common::Scratch;

/// Held by the tests that open pseudo-terminals. A controller that dies leaves its host
/// reopening the terminal's old path (`/dev/pts/N`), which the kernel may hand to another
/// test's new terminal meanwhile: the host would then hold that one (and its exclusive lock).
static PTYS: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn ptys() -> std::sync::MutexGuard<'static, ()> {
    PTYS.lock().unwrap_or_else(|e| e.into_inner())
}

fn scratch(name: &str) -> Scratch {
    Scratch::new("acquire-cli", name)
}

fn lightrig(args: &[&str]) -> Output {
    // No terminal: a step that needs a person must not wait for one.
    Command::new(env!("CARGO_BIN_EXE_lightrig")).args(args).stdin(Stdio::null()).output().unwrap()
}

/// The example rig `name` with each `(line start, replacement line)` swapped in; each must
/// match exactly one line, so a changed example fails here rather than running its full plan.
fn example(dir: &Path, name: &str, edits: &[(&str, &str)]) -> PathBuf {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs").join(name);
    let mut lines: Vec<String> = std::fs::read_to_string(&src).unwrap().lines().map(str::to_string).collect();
    for (start, with) in edits {
        let hits: Vec<usize> = (0..lines.len()).filter(|&i| lines[i].starts_with(start)).collect();
        assert_eq!(hits.len(), 1, "{name}: one line starting with {start:?}");
        lines[hits[0]] = with.to_string();
    }
    let path = dir.join(name);
    std::fs::write(&path, lines.join("\n")).unwrap();
    path
}

/// Runs `lightrig acquire` and checks the session: complete, one frame per planned trigger,
/// none missing, each frame's file as journaled.
fn acquire(rig: &Path, session: &Path) -> Session {
    let out = lightrig(&["acquire", rig.to_str().unwrap(), "--session", session.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (s, _) = Session::read(session).unwrap();
    assert!(s.is_done());
    let planned: u32 = s.manifest().plan.steps.iter().flat_map(|p| &p.triggers).map(|t| t.count).sum();
    let frames = s.frame_index();
    assert!(planned > 0);
    assert_eq!(frames.len(), planned as usize, "one frame per trigger");
    assert!(s.verify().is_empty(), "{:?}", s.verify());
    assert!(!session.join("virtual-camera").exists(), "the camera's scratch files are removed");
    let said = String::from_utf8_lossy(&out.stderr);
    let tally = format!("{} frames paired with their triggers, 0 missing", frames.len());
    assert!(said.contains(&tally), "the run ends with its tally: {said}");
    assert!(!said.contains("extra-*"), "no extra frames to speak of: {said}");
    s
}

/// A camera whose frames never come (its directory stays empty): the run says so as the step
/// ends, finishes the session with them recorded missing, and exits 5, naming the step and
/// `resume --retake-missing`; `resume` on the finished session says the same.
#[test]
fn a_run_that_lost_frames_says_so_and_exits_incomplete() {
    let dir = scratch("lost");
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    let source = format!(
        "source = {{ kind = \"directory\", path = \"{}\", pattern = \"img_{{frame:06}}.png\" }}",
        frames.display()
    );
    let rig = example(
        &dir,
        "lls-gantry.toml",
        &[
            ("source", &source),
            ("pass_mm", "pass_mm = [-2, 2]"),
            ("step_mm", "step_mm = 2"),
            ("passes", "passes = [\"reflectance\"]"),
            ("exposures_us", "exposures_us = [500]"),
        ],
    );
    let session = dir.join("session");
    let out = lightrig(&["acquire", rig.to_str().unwrap(), "--session", session.to_str().unwrap()]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(5), "{said}");
    assert!(
        said.contains("warning: step 0 (pass reflectance): 3 of 3 frames missing (camera 0 frame 0: "),
        "warned as the step ended: {said}"
    );
    assert!(said.contains("3 MISSING"), "the progress line counts them: {said}");
    assert!(
        said.contains("session complete") && said.contains("0 frames paired with their triggers, 3 missing")
    );
    assert!(
        said.contains(&format!(
            "acquire those steps again with `lightrig resume {} --retake-missing`",
            session.display()
        )),
        "{said}"
    );
    let (s, _) = Session::read(&session).unwrap();
    assert!(s.is_done());
    assert_eq!(s.steps_missing_frames().len(), 1);
    let again = lightrig(&["resume", session.to_str().unwrap()]);
    let said = String::from_utf8_lossy(&again.stderr);
    assert_eq!(again.status.code(), Some(5), "{said}");
    assert!(said.contains("with frames missing in 1 step(s)"), "{said}");
    // The fit, short of the frames it needs, names the lost ones and the command to take them.
    let fit =
        lightrig(&["fit", "lls", session.to_str().unwrap(), "--out", dir.join("fit").to_str().unwrap()]);
    let said = String::from_utf8_lossy(&fit.stderr);
    assert_eq!(fit.status.code(), Some(1), "{said}");
    let expected = format!(
        "the session has frames missing in 1 step(s):\n  step 0: 3 frame(s) missing (camera 0 frame 0: \
         no frame arrived within the wait)\nacquire those steps again with `lightrig resume {} --retake-missing`",
        session.display()
    );
    assert!(said.contains(&expected), "expected {expected:?} in:\n{said}");
}

#[test]
fn a_missing_camera_response_is_refused_before_the_session_starts() {
    let dir = scratch("response");
    let rig = example(
        &dir,
        "lls-gantry.toml",
        &[("min_interval_us", "min_interval_us = 50000\nresponse = \"cam0-response.json\"")],
    );
    let session = dir.join("session");
    let out = lightrig(&["acquire", rig.to_str().unwrap(), "--session", session.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(4));
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(
        said.contains(&format!("{}", dir.join("cam0-response.json").display()))
            && said.contains("lightrig hdr calibrate"),
        "{said}"
    );
    assert!(!session.join("manifest.json").exists(), "no session is started");
}

/// Plan values and the fit's `[plan.fit]` are checked before anything connects or moves, each
/// error naming the key the user wrote, its line and what is allowed (before, a pass beyond the
/// gantry's limits named the stepper after 10 s of homing, and a broken [plan.fit] surfaced
/// only in the fit after the whole acquisition).
#[test]
fn plan_values_and_the_fit_table_are_checked_before_anything_moves() {
    let dir = scratch("values");
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/lls-gantry.toml");
    let r = rig.to_str().unwrap();
    let at = |line: usize| format!("lls-gantry.toml:{line}: ");
    let cases: [(&str, String); 8] = [
        (
            "plan.pass_mm=[-300, 100]",
            at(70) + "plan.pass_mm: -300 mm is outside the limits -200..=200 mm (the gantry's [[stepper]] limits)",
        ),
        ("plan.pass_mm=[-100, 250]", at(70) + "plan.pass_mm: 250 mm is outside the limits -200..=200 mm"),
        (
            "plan.exposures_us=[-5, 100]",
            at(72) + "plan.exposures_us: -5 µs is out of range: give a duration from 0 to 4294967295 µs",
        ),
        (
            "plan.fit.stripe.offset_m=3",
            at(81) + "plan.fit: unknown field `offset_m`, expected `offset_mm` or `angle_deg`",
        ),
        ("plan.fit.light=", at(81) + "plan.fit: missing field `light`"),
        (
            "laser[1].role=",
            at(76)
                + "plan.passes: a reflectance pass needs the [[laser]] with `role = \"tube\"`; the rig's lasers: \
                   channel 0 `stripe` (role stripe), channel 1 `light-tube` (no role)",
        ),
        (
            // A lab's own camera on the virtual rig, whose camera renders its own.
            "plan.fit.camera.cx=639.5",
            "lls-gantry.toml: camera 0 is virtual, and the virtual rig renders its own fixed scene \
             (docs/virtual-rig.md), not what [plan.fit] describes: plan.fit.camera.cx = 639.5 (the virtual \
             rig's: 63.5)"
                .to_string(),
        ),
        (
            "laser[1].role=\"tub\"",
            at(50) + "laser[1].role: unknown value \"tub\"; did you mean \"tube\"?",
        ),
    ];
    for (k, (set, expected)) in cases.iter().enumerate() {
        let session = dir.join(format!("s{k}"));
        let out = lightrig(&["acquire", r, "--session", session.to_str().unwrap(), "--set", set]);
        let said = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(4), "--set {set}: {said}");
        assert!(said.contains(expected.as_str()), "--set {set}: expected {expected:?} in:\n{said}");
        assert!(
            !said.contains("homing") && !session.exists(),
            "--set {set}: refused before bring-up: {said}"
        );
    }
    // A goniometer angle beyond the light arm's limits: the plan key, not the stepper.
    let bispectral = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/bispectral.toml");
    let session = dir.join("gonio");
    let set = "plan.gonio.light_angles=[30, 200]";
    let out = lightrig(&[
        "acquire",
        bispectral.to_str().unwrap(),
        "--session",
        session.to_str().unwrap(),
        "--set",
        set,
    ]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(4), "{said}");
    let expected =
        "bispectral.toml:130: plan.gonio.light_angles: 200 deg is outside the limits -170..=170 deg \
                    (stepper `light-arm`'s limits)";
    assert!(said.contains(expected), "expected {expected:?} in:\n{said}");
    assert!(!said.contains("homing") && !session.exists(), "refused before bring-up: {said}");
    // Without [plan.fit] the acquisition runs (it needs none), saying at once that the fit will
    // refuse the session.
    let session = dir.join("no-fit");
    let s = session.to_str().unwrap();
    let mut args = vec!["acquire", r, "--session", s, "--set", "plan.fit=", "--set", "plan.pass_mm=[-4, 4]"];
    args.extend(["--set", "plan.step_mm=4", "--set", "plan.passes=[\"reflectance\"]"]);
    let out = lightrig(&args);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{said}");
    let warning =
        "no [plan.fit] table: the acquisition runs, but `lightrig fit` will refuse the session without \
                   the tube's and the stripe's geometry";
    let (w, h) = (said.find(warning), said.find("homing"));
    assert!(w.is_some() && w < h, "warned before bring-up: {said}");
}

#[test]
fn overrides_shape_the_run_and_resume_asks_for_the_same_ones() {
    let dir = scratch("overrides");
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/lls-gantry.toml");
    let (r, session) = (rig.to_str().unwrap(), dir.join("session"));
    let s = session.to_str().unwrap();
    let sets = [
        "--set",
        "plan.pass_mm=[-4, 4]",
        "--set",
        "plan.step_mm=4",
        "--set",
        "plan.passes=[\"reflectance\"]",
    ];
    let mut args = vec!["acquire", r, "--session", s];
    args.extend(sets);
    let out = lightrig(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // 3 positions × the shipped 3-exposure bracket.
    let (done, _) = Session::read(&session).unwrap();
    assert_eq!(done.frame_index().len(), 9);
    let text = &done.manifest().rig;
    assert!(text.contains("step_mm = 4") && text.ends_with("#   plan.passes=[\"reflectance\"]\n"), "{text}");
    // Resuming against the original file needs the same overrides.
    let out = lightrig(&["resume", s, "--rig", r]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(said.contains("already complete"), "a complete session is not re-checked: {said}");
    // A misspelt plan key is refused before anything connects or moves, not ignored.
    let typo = dir.join("s3");
    let bad = lightrig(&["acquire", r, "--session", typo.to_str().unwrap(), "--set", "plan.step_m=4"]);
    let said = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(bad.status.code(), Some(4), "{said}");
    assert!(said.contains("plan.step_m: unknown key; did you mean \"step_mm\"?"), "{said}");
    assert!(!said.contains("homing") && !typo.exists(), "refused before bring-up: {said}");
    let bad =
        lightrig(&["acquire", r, "--session", dir.join("s2").to_str().unwrap(), "--set", "plan.nope.x="]);
    let said = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(bad.status.code(), Some(4), "{said}");
    assert!(
        said.contains("lls-gantry.toml: --set plan.nope.x=: the file has no `plan.nope.x` to remove"),
        "{said}"
    );
}

#[test]
fn bispectral_example_acquires_with_its_filters_set_before_each_step() {
    let dir = scratch("bispectral");
    let rig = example(
        &dir,
        "bispectral.toml",
        &[
            ("range_nm", "range_nm = [400, 410]"),
            ("sample_angles", "sample_angles = [0]"),
            ("light_angles", "light_angles = [30]"),
        ],
    );
    // Its 20 ms exposures are far shorter than the camera's 250 ms minimum interval: the plan
    // must wait for the camera, or the device refuses the trigger (`TriggerTooSoon`).
    let session = dir.join("session");
    let s = acquire(&rig, &session);
    let prepared: Vec<(u32, String, Vec<String>)> = journal_records(&session)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            Record::StepPrepared { step, by, actions, .. } => Some((step, by, actions)),
            _ => None,
        })
        .collect();
    assert_eq!(prepared.len(), s.manifest().plan.steps.len(), "every step sets the tunable filters");
    let first = &prepared[0];
    assert_eq!(first.1, "virtual");
    assert!(first.2.iter().any(|a| a.starts_with("set the camera filter to ")), "{:?}", first.2);
    assert!(first.2.iter().any(|a| a.starts_with("set the light filter to ")), "{:?}", first.2);
}

#[test]
fn bispectral_filters_on_serial_ports_are_tuned_by_the_host() {
    use lightrig_sim::filter::PtyFilter;
    let _ptys = ptys();
    let dir = scratch("bispectral-ports");
    let settle = std::time::Duration::from_millis(2);
    let (light, camera) = (
        PtyFilter::start((350.0, 720.0), settle, false).unwrap(),
        PtyFilter::start((400.0, 720.0), settle, false).unwrap(),
    );
    let ports = format!(
        "settle_ms = 0\nlight_range_nm = [350, 720]\nlight_port = \"{}\"\ncamera_port = \"{}\"",
        light.path().display(),
        camera.path().display()
    );
    let rig = example(
        &dir,
        "bispectral.toml",
        &[
            ("range_nm", "range_nm = [400, 410]"),
            ("settle_ms", &ports),
            ("sample_angles", "sample_angles = [0]"),
            ("light_angles", "light_angles = [30]"),
        ],
    );
    let session = dir.join("session");
    let s = acquire(&rig, &session);
    let steps = s.manifest().plan.steps.len();
    let by = lightrig_host::session::prepared_by(&session).unwrap();
    assert_eq!(by, vec!["instruments".to_string(); steps]);
    // Each step's pair, in plan order, reached the filters.
    let wanted: Vec<(f64, f64)> = s
        .manifest()
        .plan
        .steps
        .iter()
        .map(|p| {
            let host = &p.extra["meta"]["host"];
            (host["light_filter_nm"].as_f64().unwrap(), host["camera_filter_nm"].as_f64().unwrap())
        })
        .collect();
    let got: Vec<(f64, f64)> = light.tuned().into_iter().zip(camera.tuned()).collect();
    assert_eq!(got, wanted);
}

/// The DISCO example at 192 × 124 pixels (its focal length scaled to match).
const DISCO_SMALL: [(&str, &str); 2] = [("image", "image = [192, 124]"), ("focal_px", "focal_px = 450")];

/// Where the virtual DISCO camera sees the beam at galvo `code` enter the pebble (camera
/// position `position`, turntable at `deg`): `Some(pixel)` if it enters and the camera sees the
/// entry point, `None` if it misses the object; `Some(None)` if hidden.
fn disco_spot(rig: &Path, code: [u16; 2], position: usize, deg: f64) -> Option<Option<[f64; 2]>> {
    use lightrig_pipelines::disco::optics::{cast, point_of, surface_map};
    use lightrig_pipelines::vec3::{norm, sub};
    let rig = lightrig_host::rigfile::RigFile::load(rig).unwrap();
    let scene = lightrig_sim::scenes::disco::DiscoScene::new(&rig, 3).unwrap();
    let world = lightrig_pipelines::disco::optics::turned(&scene.mesh, deg);
    let p = &scene.setup.projector;
    let hit = cast(&scene.mesh, &world, p.eye, p.ray([f64::from(code[0]), f64::from(code[1])]))?;
    let (entry, _) = point_of(&scene.mesh, &world, deg, &hit);
    let cam = scene.setup.cameras[position].1;
    let (px, _) = cam.project(entry)?;
    let map = surface_map(&scene.mesh, &world, &cam);
    let seen = map[px[1] as usize * cam.width as usize + px[0] as usize]
        .is_some_and(|h| norm(sub(point_of(&scene.mesh, &world, deg, &h).0, entry)) < 1.0);
    Some(seen.then_some(px))
}

#[test]
fn disco_frames_show_the_spot_where_each_trigger_pointed_the_galvos() {
    let dir = scratch("disco");
    let mut edits = vec![("views", "views = 1"), ("spot_grid", "spot_grid = [5, 3]")];
    edits.extend(DISCO_SMALL);
    let rig = example(&dir, "disco.toml", &edits);
    let session = dir.join("session");
    let s = acquire(&rig, &session);
    let triggers = trigger_events(&session).unwrap();
    let (mut seen, mut missed, mut white, mut registration) = (0, 0, 0, 0);
    for f in s.frame_index() {
        let t = &triggers[&(f.sequence, f.item)];
        let img = lightrig_imaging::io::read(session.join(&f.file)).unwrap();
        assert_eq!(img.channels, 1, "a grey HDR camera");
        let w = img.width as usize;
        let (best, at) =
            img.data.iter().enumerate().fold((f32::MIN, 0), |b, (i, &v)| if v > b.0 { (v, i) } else { b });
        let at = [(at % w) as f64 + 0.5, (at / w) as f64 + 0.5];
        let step = &s.manifest().plan.steps[f.step as usize];
        let meta = &step.extra["meta"];
        let g = t.snapshot.galvos[0];
        assert_eq!(t.snapshot.lasers.count_ones(), 1, "one laser at a time");
        if meta["kind"] == "white" {
            // The white target, lit at the zero codes.
            white += 1;
            assert_eq!([g.x, g.y], [32768, 32768]);
            assert!(best > 1.0, "{best}");
            continue;
        }
        if t.snapshot.lasers == 1 << 3 {
            // The registration frame: the spotlights light the whole pebble, the room is dark.
            registration += 1;
            let lit = img.data.iter().filter(|&&v| v > 1.0).count();
            assert!(lit > img.data.len() / 20 && img.data[0] < 0.01, "{lit} pixels lit");
            continue;
        }
        let position = meta["camera_position"].as_u64().unwrap() as usize;
        match disco_spot(&rig, [g.x, g.y], position, 0.0) {
            None => {
                // The beam misses the object: the frame holds only the sensor's read noise.
                missed += 1;
                assert!(best < 0.01, "frame {}: {best}", f.frame);
            }
            Some(Some(want)) => {
                seen += 1;
                let d = ((at[0] - want[0]).powi(2) + (at[1] - want[1]).powi(2)).sqrt();
                assert!(d <= 1.5, "frame {}: peak {at:?}, spot at {want:?}", f.frame);
                assert!(best > 100.0, "{best}");
            }
            Some(None) => {}
        }
    }
    assert_eq!(white, 3, "a white-balance frame per laser");
    assert_eq!(registration, 2, "a registration frame per view and camera position");
    // 15 spots × 3 lasers at each of 2 camera positions: some hit and are seen, the grid's
    // corners miss the pebble.
    assert!(seen >= 6 && missed >= 6, "seen {seen}, missed {missed}");
}

#[cfg(unix)]
#[test]
fn a_step_that_needs_a_person_stops_without_a_terminal_and_runs_with_yes() {
    let _ptys = ptys();
    let dir = scratch("operator");
    // The board pass asks the operator to place the calibration board. No homing: the device
    // runs in real time behind the pseudo-terminal.
    let rig = example(
        &dir,
        "lls-gantry.toml",
        &[
            ("homing", "homing = { mode = \"none\" }"),
            ("pass_mm", "pass_mm = [-4, 4]"),
            ("passes", "passes = [\"board\"]"),
            ("exposures_us", "exposures_us = [500]"),
        ],
    );
    let link = dir.join("rig-tty");
    let mut sim = sim_on(&rig, &link);
    let connect = format!("serial:{}", link.display());
    let session = dir.join("session");
    let s = session.to_str().unwrap();

    let refused = lightrig(&["acquire", rig.to_str().unwrap(), "--session", s, "--connect", &connect]);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert_eq!(refused.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("needs a person: place the calibration board"), "{stderr}");
    assert!(stderr.contains("--yes"), "{stderr}");
    let (before, _) = Session::read(&session).unwrap();
    assert!(before.frame_index().is_empty() && before.open_attempt().is_none(), "nothing started");

    let done = lightrig(&["resume", s, "--rig", rig.to_str().unwrap(), "--connect", &connect, "--yes"]);
    let _ = sim.kill();
    let _ = sim.wait();
    assert!(done.status.success(), "{}", String::from_utf8_lossy(&done.stderr));
    let (after, _) = Session::read(&session).unwrap();
    assert!(after.is_done());
    assert_eq!(after.frame_index().len(), 1);
    let by = lightrig_host::session::prepared_by(&session).unwrap();
    assert_eq!(by, ["assumed"]);
}

/// A second `[[camera]]` for the DISCO example (the same virtual source), before its `[plan]`.
const SIDE_CAMERA: &str = "[[camera]]
camera = 1
name = \"side\"
pulse_us = 100
polarity = \"high\"
exposure_input = \"unused\"
min_interval_us = 60000
source = { kind = \"virtual\" }

[plan]";

#[test]
fn every_camera_of_the_rig_fires_at_every_spot_unless_the_plan_picks_some() {
    let dir = scratch("two-cameras");
    let rig = example(
        &dir,
        "disco.toml",
        &[
            ("views", "views = 1"),
            ("spot_grid", "spot_grid = [2, 2]"),
            ("[plan]", SIDE_CAMERA),
            ("white_balance", "white_balance = false"),
            DISCO_SMALL[0],
            DISCO_SMALL[1],
        ],
    );
    let session = dir.join("session");
    let s = acquire(&rig, &session);
    // The registration frame and 4 spots × 3 lasers, on each camera (at each of the two camera
    // positions).
    let step = &s.manifest().plan.steps[0];
    assert_eq!((step.expected(0), step.expected(1)), (13, 13));
    let triggers = trigger_events(&session).unwrap();
    let mut by_camera: [Vec<(u64, [u16; 2], u8)>; 2] = [Vec::new(), Vec::new()];
    for f in s.frame_index() {
        let t = &triggers[&(f.sequence, f.item)];
        assert_eq!(t.camera, f.camera);
        let g = t.snapshot.galvos[0];
        by_camera[usize::from(f.camera)].push((t.tick, [g.x, g.y], t.snapshot.lasers));
        if t.snapshot.lasers == 1 << 3 {
            continue; // the registration frame: no spot
        }
        // Both cameras render the spot where the trigger pointed the galvos.
        let img = lightrig_imaging::io::read(session.join(&f.file)).unwrap();
        let w = img.width as usize;
        let peak = (0..img.data.len()).max_by(|&a, &b| img.data[a].total_cmp(&img.data[b])).unwrap();
        let position =
            s.manifest().plan.steps[f.step as usize].extra["meta"]["camera_position"].as_u64().unwrap();
        if let Some(Some(want)) = disco_spot(&rig, [g.x, g.y], position as usize, 0.0) {
            let at = ((peak % w) as f64 + 0.5, (peak / w) as f64 + 0.5);
            let d = ((at.0 - want[0]).powi(2) + (at.1 - want[1]).powi(2)).sqrt();
            assert!(d <= 1.5, "cam {}: {at:?} vs {want:?}", f.camera);
        }
    }
    for list in &mut by_camera {
        list.sort();
    }
    // The same instants, the same spots, the same lasers: one exposure seen by two cameras.
    assert_eq!(by_camera[0].len(), 26);
    assert_eq!(by_camera[0], by_camera[1]);
    // The side camera's 60 ms minimum interval sets the spacing of both.
    let ticks: Vec<u64> = by_camera[0].iter().map(|t| t.0).collect();
    let tick_hz = s.manifest().device.tick_hz;
    assert!(ticks.windows(2).all(|w| w[1] - w[0] >= 60_000 * u64::from(tick_hz) / 1_000_000), "{ticks:?}");

    // `[plan] cameras` picks: only the side camera fires.
    let dir = scratch("picked-camera");
    let rig = example(
        &dir,
        "disco.toml",
        &[
            ("views", "views = 1\ncameras = [\"side\"]"),
            ("spot_grid", "spot_grid = [2, 2]"),
            ("[plan]", SIDE_CAMERA),
            ("white_balance", "white_balance = false"),
            DISCO_SMALL[0],
            DISCO_SMALL[1],
        ],
    );
    let s = acquire(&rig, &dir.join("session"));
    let step = &s.manifest().plan.steps[0];
    assert_eq!((step.expected(0), step.expected(1)), (0, 13));
    assert!(s.frame_index().iter().all(|f| f.camera == 1));
}

/// `lightrig sim --pty --link PATH` on `rig`, once its terminal is up.
#[cfg(unix)]
fn sim_on(rig: &Path, link: &Path) -> std::process::Child {
    use std::io::{BufRead, BufReader};
    let mut sim = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["sim", "--pty", "--seconds", "120", "--rig", rig.to_str().unwrap(), "--link"])
        .arg(link)
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(sim.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(!line.trim().is_empty(), "the simulator printed its terminal");
    sim
}
