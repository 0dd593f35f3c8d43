//! `lightrig acquire` end to end on every example rig file in `docs/rigs/`, as a newcomer runs
//! it: `connect = "virtual"` and `source = { kind = "virtual" }`, each plan cut down to a few
//! frames. Every session must complete with one frame per trigger; the DISCO frames must show
//! the laser spot where the trigger's galvo codes pointed; steps that ask for a person or a
//! host instrument are journaled, refused without a terminal, and taken as done with `--yes`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use lightrig_host::session::{journal_records, trigger_events, Record, Session};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lightrig-acquire-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
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
    s
}

#[test]
fn linear_light_source_example_acquires() {
    let dir = scratch("lls");
    let rig =
        example(&dir, "lls-gantry.toml", &[("pass_mm", "pass_mm = [-4, 4]"), ("step_mm", "step_mm = 4")]);
    let s = acquire(&rig, &dir.join("session"));
    // Two passes (reflectance, stripe) × 3 positions × the 3-exposure bracket.
    assert_eq!(s.frame_index().len(), 18);
}

#[test]
fn fluorescent_immersion_example_acquires() {
    let dir = scratch("firs");
    let rig = example(
        &dir,
        "fluorescent-immersion.toml",
        &[("views", "views = 1"), ("sheet_positions", "sheet_positions = 6")],
    );
    acquire(&rig, &dir.join("session"));
}

#[test]
fn brdf_display_example_acquires() {
    let dir = scratch("brdf");
    let rig = example(&dir, "brdf-display.toml", &[]);
    acquire(&rig, &dir.join("session"));
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
fn disco_frames_show_the_spot_where_each_trigger_pointed_the_galvos() {
    let dir = scratch("disco");
    let rig = example(&dir, "disco.toml", &[("views", "views = 1"), ("spot_grid", "spot_grid = [3, 2]")]);
    let session = dir.join("session");
    let s = acquire(&rig, &session);
    let triggers = trigger_events(&session).unwrap();
    let mut spots = 0;
    for f in s.frame_index() {
        let t = &triggers[&(f.sequence, f.item)];
        let img = lightrig_imaging::io::read(session.join(&f.file)).unwrap();
        let (w, h) = (img.width as usize, img.height as usize);
        let px = |x: usize, y: usize| &img.data[(y * w + x) * 3..(y * w + x) * 3 + 3];
        let (mut best, mut at) = (0.0f32, (0, 0));
        for y in 0..h {
            for x in 0..w {
                let v: f32 = px(x, y).iter().sum();
                if v > best {
                    (best, at) = (v, (x, y));
                }
            }
        }
        if t.snapshot.lasers == 0 {
            continue;
        }
        spots += 1;
        // The card maps code c to c·size/65536 (continuous, pixel centres at +0.5).
        let g = t.snapshot.galvos[0];
        let want = (f64::from(g.x) * w as f64 / 65536.0, f64::from(g.y) * h as f64 / 65536.0);
        let (dx, dy) = (at.0 as f64 + 0.5 - want.0, at.1 as f64 + 0.5 - want.1);
        assert!(dx.abs() <= 1.0 && dy.abs() <= 1.0, "frame {}: peak {at:?}, spot at {want:?}", f.frame);
        // In the laser's colour: 635 nm (channel 0) red, 532 nm green, 476 nm blue.
        let c = px(at.0, at.1);
        let dominant = (0..3).max_by(|&a, &b| c[a].total_cmp(&c[b])).unwrap();
        assert_eq!(1u8 << dominant, t.snapshot.lasers, "frame {}: {c:?}", f.frame);
    }
    // 6 spots × 3 lasers; the registration frame has no laser.
    assert_eq!(spots, 18);
}

#[cfg(unix)]
#[test]
fn a_step_that_needs_a_person_stops_without_a_terminal_and_runs_with_yes() {
    use std::io::{BufRead, BufReader};
    let dir = scratch("operator");
    // The board pass asks the operator to place the calibration board. No homing: the device
    // runs in real time behind the pseudo-terminal.
    let rig = example(
        &dir,
        "lls-gantry.toml",
        &[
            ("homing", "homing = { mode = \"none\" }"),
            ("pass_mm", "pass_mm = [-4, 4]\npasses = [\"board\"]"),
            ("exposures_us", "exposures_us = [500]"),
        ],
    );
    let mut sim = Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .args(["sim", "--pty", "--seconds", "120", "--rig", rig.to_str().unwrap()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(sim.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let connect = format!("serial:{}", line.trim());
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
    let by: Vec<String> = journal_records(&session)
        .unwrap()
        .into_iter()
        .filter_map(|r| match r {
            Record::StepPrepared { by, .. } => Some(by),
            _ => None,
        })
        .collect();
    assert_eq!(by, ["assumed"]);
}
