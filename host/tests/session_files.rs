//! Session files as input (issue 51, part 4): a session writes only its own regular files and
//! folders. A symbolic link (or a second name, a hard link) planted where the session writes,
//! temporaries included, is refused with an error naming the path, and nothing outside the
//! session changes: not the link's target, byte for byte, and `manifest.json` stays a regular
//! file.

#![cfg(unix)]

use std::fs;
use std::os::unix::fs::symlink;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::session::{
    encode_line, write_session_file, Extra, ExtraReason, Pair, Session, SessionError, Trigger, JOURNAL,
    MANIFEST,
};

#[path = "support/sessions.rs"]
mod sessions;
use sessions::{event_record, manifest, plan, trigger_event, triggers_of};

/// What a file outside the session holds; it must hold it still after every refusal.
const VICTIM: &[u8] = b"a file outside the session: it must stay exactly as it is\n";

/// A scratch place with a session directory (not created) and, beside it, a directory that
/// stands for everything outside the session, holding one file, `victim`.
struct Scene {
    root: PathBuf,
    dir: PathBuf,
    outside: PathBuf,
}

impl Scene {
    fn new(name: &str) -> Scene {
        static N: AtomicU32 = AtomicU32::new(0);
        let root = std::env::temp_dir().join(format!(
            "lightrig-session-files-{name}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = fs::remove_dir_all(&root);
        let (dir, outside) = (root.join("session"), root.join("outside"));
        fs::create_dir_all(&outside).unwrap();
        fs::write(outside.join("victim"), VICTIM).unwrap();
        Scene { root, dir, outside }
    }

    fn victim(&self) -> PathBuf {
        self.outside.join("victim")
    }

    /// Everything under `outside/`, relative paths with their content (folders as `None`).
    fn outside_contents(&self) -> Vec<(String, Option<Vec<u8>>)> {
        fn walk(base: &Path, at: &Path, out: &mut Vec<(String, Option<Vec<u8>>)>) {
            let mut entries: Vec<_> = fs::read_dir(at).unwrap().map(|e| e.unwrap().path()).collect();
            entries.sort();
            for p in entries {
                let rel = p.strip_prefix(base).unwrap().display().to_string();
                let m = fs::symlink_metadata(&p).unwrap();
                if m.is_dir() {
                    out.push((rel, None));
                    walk(base, &p, out);
                } else {
                    out.push((rel, Some(fs::read(&p).unwrap())));
                }
            }
        }
        let mut out = Vec::new();
        walk(&self.outside, &self.outside, &mut out);
        out
    }

    /// The victim file is byte for byte what it was, and nothing else appeared outside.
    fn assert_outside_untouched(&self) {
        assert_eq!(
            fs::read(self.victim()).unwrap(),
            VICTIM,
            "{}: the file outside the session was written",
            self.victim().display()
        );
        let names: Vec<String> = self.outside_contents().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, vec!["victim".to_string()], "files appeared outside the session");
    }

    /// `manifest.json` is a regular file (not a link), if it exists at all.
    fn assert_manifest_regular(&self) {
        match fs::symlink_metadata(self.dir.join(MANIFEST)) {
            Ok(m) => assert!(m.file_type().is_file(), "manifest.json is no longer a regular file: {m:?}"),
            Err(e) => assert_eq!(e.kind(), std::io::ErrorKind::NotFound, "{e}"),
        }
    }
}

impl Drop for Scene {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.root);
    }
}

/// `r` failed with `SessionError::Foreign` naming `path` (and, for a symbolic link, where it
/// points, and what to do); returns the message.
fn assert_refused<T: std::fmt::Debug>(
    r: Result<T, SessionError>,
    path: &Path,
    target: Option<&Path>,
) -> String {
    let e = r.expect_err("the session wrote through a planted link instead of refusing");
    let msg = e.to_string();
    // Shown with --nocapture: what an operator reads.
    eprintln!("refused: {msg}");
    assert!(matches!(&e, SessionError::Foreign { path: p, .. } if p == path), "{e:?}: {msg}");
    assert!(msg.contains(&path.display().to_string()), "the message names the path: {msg}");
    if let Some(t) = target {
        assert!(msg.contains("symbolic link"), "{msg}");
        assert!(msg.contains(&t.display().to_string()), "the message says where the link points: {msg}");
    }
    assert!(msg.contains("run again"), "the message says what to do: {msg}");
    msg
}

/// A trigger of step `step`'s plan: camera 0, frame `frame`.
fn trigger(frame: u32) -> Trigger {
    Trigger { sequence: 1, item: frame, camera: 0, frame, tick: 1_000 + u64::from(frame), host_us: None }
}

fn pair(frame: u32) -> Pair {
    Pair { trigger: trigger(frame), arrival: frame as usize, arrived_us: 10.0, delay_us: None, late: false }
}

/// A session of two steps of one camera's `frames` frames, step 10 done (all its frames stored).
fn session_with_a_done_step(dir: &Path, frames: u32) -> Session {
    let mut s = Session::create(dir, manifest(plan(2, 1, frames))).unwrap();
    s.device_connected(&virtual_device_info()).unwrap();
    let step = s.manifest().plan.steps[0].clone();
    s.start_step(step.id, 1).unwrap();
    for (i, t) in triggers_of(&step, 1).iter().enumerate() {
        s.record_event(&event_record(7, i as u32, trigger_event(t))).unwrap();
    }
    for f in 0..frames {
        s.store_frame(&pair(f), "raw", &[f as u8; 100]).unwrap();
    }
    s.finish_step().unwrap();
    s
}

fn set_format(dir: &Path, format: u32) {
    let path = dir.join(MANIFEST);
    let mut m: serde_json::Value = serde_json::from_slice(&fs::read(&path).unwrap()).unwrap();
    m["format"] = format.into();
    fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

fn format_of(dir: &Path) -> u64 {
    let m: serde_json::Value = serde_json::from_slice(&fs::read(dir.join(MANIFEST)).unwrap()).unwrap();
    m["format"].as_u64().unwrap()
}

// ---------------------------------------------------------------------------------------------
// manifest.json.partial

#[test]
fn create_refuses_a_linked_manifest_partial() {
    let sc = Scene::new("create");
    fs::create_dir_all(&sc.dir).unwrap();
    let link = sc.dir.join("manifest.json.partial");
    symlink(sc.victim(), &link).unwrap();
    assert_refused(Session::create(&sc.dir, manifest(plan(1, 1, 1))), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    sc.assert_manifest_regular();
    assert!(fs::symlink_metadata(sc.dir.join(MANIFEST)).is_err(), "no manifest written");

    // A link to a file that does not exist yet: not created.
    fs::remove_file(&link).unwrap();
    let absent = sc.outside.join("new-file");
    symlink(&absent, &link).unwrap();
    assert_refused(Session::create(&sc.dir, manifest(plan(1, 1, 1))), &link, Some(&absent));
    assert!(fs::symlink_metadata(&absent).is_err(), "the link's target was created");
    sc.assert_outside_untouched();
    sc.assert_manifest_regular();

    // What the message says to do works; a regular leftover of a create that stopped is
    // replaced.
    fs::remove_file(&link).unwrap();
    fs::write(&link, b"half a manifest").unwrap();
    drop(Session::create(&sc.dir, manifest(plan(1, 1, 1))).unwrap());
    sc.assert_manifest_regular();
    assert!(fs::symlink_metadata(&link).is_err(), "the leftover is gone");
    Session::read(&sc.dir).unwrap();
}

#[test]
fn resume_refuses_a_linked_manifest_partial_when_it_raises_the_format() {
    let sc = Scene::new("upgrade");
    drop(Session::create(&sc.dir, manifest(plan(1, 1, 1))).unwrap());
    set_format(&sc.dir, 3);
    let journal = fs::read(sc.dir.join(JOURNAL)).unwrap();
    let link = sc.dir.join("manifest.json.partial");
    symlink(sc.victim(), &link).unwrap();
    assert_refused(Session::open(&sc.dir), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    sc.assert_manifest_regular();
    assert_eq!(format_of(&sc.dir), 3, "the manifest unchanged");
    assert_eq!(fs::read(sc.dir.join(JOURNAL)).unwrap(), journal, "the journal unchanged");

    fs::remove_file(&link).unwrap();
    drop(Session::open(&sc.dir).unwrap());
    assert_eq!(format_of(&sc.dir), u64::from(lightrig_host::session::FORMAT_VERSION));
    sc.assert_manifest_regular();
}

#[test]
fn retaking_missing_frames_refuses_a_linked_manifest_partial() {
    let sc = Scene::new("retake");
    // A finished session of format 3 with a missing frame: `resume --retake-missing` raises
    // the format itself (opening a done session does not).
    let mut s = Session::create(&sc.dir, manifest(plan(1, 1, 2))).unwrap();
    s.start_step(10, 1).unwrap();
    s.store_frame(&pair(0), "raw", &[1; 10]).unwrap();
    s.frame_missing(&trigger(1), "no frame").unwrap();
    s.finish_step().unwrap();
    s.finish().unwrap();
    drop(s);
    set_format(&sc.dir, 3);
    let link = sc.dir.join("manifest.json.partial");
    symlink(sc.victim(), &link).unwrap();
    let (mut s, _) = Session::open(&sc.dir).unwrap();
    let journal = fs::read(sc.dir.join(JOURNAL)).unwrap();
    assert_refused(s.reopen_missing(), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    sc.assert_manifest_regular();
    assert_eq!(format_of(&sc.dir), 3);
    assert_eq!(fs::read(sc.dir.join(JOURNAL)).unwrap(), journal, "no StepReopened written");
}

// ---------------------------------------------------------------------------------------------
// journal.jsonl.dropped.N.partial

/// The journal with one byte of an early line's JSON changed: damage with intact lines after.
fn damage_inside(dir: &Path) -> Vec<u8> {
    let path = dir.join(JOURNAL);
    let mut bytes = fs::read(&path).unwrap();
    let second = bytes.iter().position(|&b| b == b'\n').unwrap() + 1;
    bytes[second + 12] ^= 0x20;
    fs::write(&path, &bytes).unwrap();
    bytes
}

#[test]
fn dropping_a_damaged_tail_refuses_a_linked_dropped_partial() {
    let sc = Scene::new("dropped");
    drop(session_with_a_done_step(&sc.dir, 3));
    let journal = damage_inside(&sc.dir);
    // An earlier drop kept its bytes in .dropped.1: this one goes to .dropped.2.
    let earlier = sc.dir.join(format!("{JOURNAL}.dropped.1"));
    fs::write(&earlier, b"bytes dropped before\n").unwrap();
    let link = sc.dir.join(format!("{JOURNAL}.dropped.2.partial"));
    symlink(sc.victim(), &link).unwrap();
    assert_refused(Session::open_dropping_damage(&sc.dir), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    sc.assert_manifest_regular();
    assert_eq!(fs::read(sc.dir.join(JOURNAL)).unwrap(), journal, "the journal is not cut");
    assert_eq!(fs::read(&earlier).unwrap(), b"bytes dropped before\n");
    assert!(fs::symlink_metadata(sc.dir.join(format!("{JOURNAL}.dropped.2"))).is_err());

    // Once the link is gone, the drop goes ahead.
    fs::remove_file(&link).unwrap();
    let (_, rec) = Session::open_dropping_damage(&sc.dir).unwrap();
    assert_eq!(rec.saved_to.as_deref(), Some(sc.dir.join(format!("{JOURNAL}.dropped.2")).as_path()));
    sc.assert_manifest_regular();
}

#[test]
fn dropping_a_torn_tail_refuses_a_linked_dropped_partial() {
    let sc = Scene::new("torn");
    drop(session_with_a_done_step(&sc.dir, 2));
    let path = sc.dir.join(JOURNAL);
    let mut journal = fs::read(&path).unwrap();
    let line = encode_line(br#"{"type":"SessionDone","host_time":"2025-01-01T00:00:00.000Z"}"#);
    journal.extend_from_slice(&line[..line.len() / 2]);
    fs::write(&path, &journal).unwrap();
    let link = sc.dir.join(format!("{JOURNAL}.dropped.1.partial"));
    symlink(sc.victim(), &link).unwrap();
    assert_refused(Session::open(&sc.dir), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    sc.assert_manifest_regular();
    assert_eq!(fs::read(&path).unwrap(), journal, "the journal is not cut");

    // A regular leftover of a drop that stopped is replaced.
    fs::remove_file(&link).unwrap();
    fs::write(&link, b"half").unwrap();
    let (_, rec) = Session::open(&sc.dir).unwrap();
    let saved = rec.saved_to.unwrap();
    assert_eq!(fs::read(&saved).unwrap(), &line[..line.len() / 2]);
    assert!(fs::symlink_metadata(&link).is_err());
}

// ---------------------------------------------------------------------------------------------
// journal.jsonl

#[test]
fn a_linked_journal_is_refused_naming_where_it_points() {
    let sc = Scene::new("journal-link");
    drop(session_with_a_done_step(&sc.dir, 1));
    let path = sc.dir.join(JOURNAL);
    // The journal moved out (to another disk, say) and a link left in its place.
    let real = sc.outside.join(JOURNAL);
    fs::rename(&path, &real).unwrap();
    let moved = fs::read(&real).unwrap();
    symlink(&real, &path).unwrap();
    assert_refused(Session::open(&sc.dir), &path, Some(&real));
    assert_refused(Session::open_dropping_damage(&sc.dir), &path, Some(&real));
    assert_refused(Session::read(&sc.dir), &path, Some(&real));
    assert_eq!(fs::read(&real).unwrap(), moved, "the linked journal untouched");
    sc.assert_manifest_regular();

    // A link to nowhere: the journal is not created at its target.
    fs::remove_file(&path).unwrap();
    let absent = sc.outside.join("journal-to-be");
    symlink(&absent, &path).unwrap();
    assert_refused(Session::open(&sc.dir), &path, Some(&absent));
    assert!(fs::symlink_metadata(&absent).is_err(), "created through the link");
    sc.assert_manifest_regular();
}

#[test]
fn a_hard_linked_journal_is_refused() {
    let sc = Scene::new("journal-hard");
    drop(session_with_a_done_step(&sc.dir, 1));
    let path = sc.dir.join(JOURNAL);
    // A second name for the journal outside the session (`cp -al`, a backup tool): appending
    // would change that file too.
    let other = sc.outside.join("journal-backup");
    fs::hard_link(&path, &other).unwrap();
    let before = fs::read(&other).unwrap();
    let msg = assert_refused(Session::open(&sc.dir), &path, None);
    assert!(msg.contains("hard link"), "{msg}");
    assert_eq!(fs::read(&other).unwrap(), before, "the other name's file untouched");
    sc.assert_manifest_regular();
    // Reading is fine.
    Session::read(&sc.dir).unwrap();
    fs::remove_file(&other).unwrap();
    drop(Session::open(&sc.dir).unwrap());
}

// ---------------------------------------------------------------------------------------------
// Frame files

#[test]
fn a_frame_files_path_planted_as_a_link_is_refused() {
    let sc = Scene::new("frame");
    let mut s = Session::create(&sc.dir, manifest(plan(1, 1, 3))).unwrap();
    s.start_step(10, 1).unwrap();
    let attempt = sc.dir.join("frames/step-000010/attempt-01");
    fs::create_dir_all(&attempt).unwrap();
    let journal = fs::read(sc.dir.join(JOURNAL)).unwrap();

    // The temporary name of frame 0.
    let link = attempt.join("cam0-frame-000000.raw.partial");
    symlink(sc.victim(), &link).unwrap();
    assert_refused(s.store_frame(&pair(0), "raw", &[7; 64]), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    assert_eq!(fs::read(sc.dir.join(JOURNAL)).unwrap(), journal, "no Frame record written");
    fs::remove_file(&link).unwrap();
    s.store_frame(&pair(0), "raw", &[7; 64]).unwrap();

    // The final name of frame 1.
    let link = attempt.join("cam0-frame-000001.raw");
    symlink(sc.victim(), &link).unwrap();
    assert_refused(s.store_frame(&pair(1), "raw", &[8; 64]), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    assert!(fs::symlink_metadata(&link).unwrap().file_type().is_symlink(), "the link left as it was");
    fs::remove_file(&link).unwrap();

    // An extra frame's temporary name.
    let link = attempt.join("extra-0000-cam0-frame-000005.raw.partial");
    symlink(sc.victim(), &link).unwrap();
    let extra = Extra { arrival: 9, camera: 0, frame: 5, arrived_us: 1.0, reason: ExtraReason::Duplicate };
    assert_refused(s.store_extra(&extra, "raw", &[9; 64]), &link, Some(&sc.victim()));
    sc.assert_outside_untouched();
    fs::remove_file(&link).unwrap();

    // The session goes on.
    s.store_frame(&pair(1), "raw", &[8; 64]).unwrap();
    s.store_frame(&pair(2), "raw", &[9; 64]).unwrap();
    s.finish_step().unwrap();
    assert!(s.verify().is_empty());
    sc.assert_manifest_regular();
}

// ---------------------------------------------------------------------------------------------
// Folders

#[test]
fn a_linked_folder_the_session_writes_into_is_refused() {
    // Each folder on a frame's way, replaced by a link while the session is open (an
    // acquisition runs for hours; opening checked the folders before).
    for (n, rel) in ["frames", "frames/step-000010", "frames/step-000010/attempt-01"].iter().enumerate() {
        let sc = Scene::new(&format!("folder-{n}"));
        let mut s = Session::create(&sc.dir, manifest(plan(1, 1, 1))).unwrap();
        s.start_step(10, 1).unwrap();
        let path = sc.dir.join(rel);
        fs::create_dir_all(&path).unwrap();
        fs::remove_dir(&path).unwrap();
        let target = sc.outside.join("elsewhere");
        fs::create_dir(&target).unwrap();
        symlink(&target, &path).unwrap();
        assert_refused(s.store_frame(&pair(0), "raw", &[3; 32]), &path, Some(&target));
        assert!(
            fs::read_dir(&target).unwrap().next().is_none(),
            "{rel}: something was written through the link: {:?}",
            sc.outside_contents()
        );
        fs::remove_dir(&target).unwrap();
        sc.assert_outside_untouched();
        sc.assert_manifest_regular();
    }
}

#[test]
fn removing_superseded_attempts_refuses_a_linked_folder() {
    let sc = Scene::new("superseded");
    let mut s = Session::create(&sc.dir, manifest(plan(1, 1, 1))).unwrap();
    s.start_step(10, 1).unwrap();
    s.store_frame(&pair(0), "raw", &[5; 40]).unwrap();
    s.abandon_step("device fault").unwrap();
    // The step's folder moved out and a link left in its place.
    let step = sc.dir.join("frames/step-000010");
    let moved = sc.outside.join("step-000010");
    fs::rename(&step, &moved).unwrap();
    symlink(&moved, &step).unwrap();
    let before = sc.outside_contents();
    assert_eq!(before.len(), 4, "{before:?}");
    assert_refused(s.remove_superseded(), &step, Some(&moved));
    assert_eq!(sc.outside_contents(), before, "deleted through the link");

    // The attempt's folder itself a link: the link is refused too, not just removed.
    fs::remove_file(&step).unwrap();
    fs::create_dir(&step).unwrap();
    let attempt = step.join("attempt-01");
    symlink(moved.join("attempt-01"), &attempt).unwrap();
    assert_refused(s.remove_superseded(), &attempt, Some(&moved.join("attempt-01")));
    assert_eq!(sc.outside_contents(), before);
    assert!(fs::symlink_metadata(&attempt).unwrap().file_type().is_symlink());

    // Its own folder is removed.
    fs::remove_file(&attempt).unwrap();
    fs::rename(moved.join("attempt-01"), &attempt).unwrap();
    assert_eq!(s.remove_superseded().unwrap(), vec![attempt.clone()]);
    assert!(!attempt.exists());
    sc.assert_manifest_regular();
}

// ---------------------------------------------------------------------------------------------
// Files other parts of lightrig keep in a session

#[test]
fn a_session_file_beside_the_journal_refuses_a_link() {
    let sc = Scene::new("beside");
    drop(Session::create(&sc.dir, manifest(plan(1, 1, 1))).unwrap());
    for name in ["camera0-response.json", "camera0-response.json.partial"] {
        let link = sc.dir.join(name);
        symlink(sc.victim(), &link).unwrap();
        assert_refused(
            write_session_file(&sc.dir, "camera0-response.json", b"{}"),
            &link,
            Some(&sc.victim()),
        );
        sc.assert_outside_untouched();
        fs::remove_file(&link).unwrap();
    }
    write_session_file(&sc.dir, "camera0-response.json", b"{}\n").unwrap();
    assert_eq!(fs::read(sc.dir.join("camera0-response.json")).unwrap(), b"{}\n");
    for bad in [MANIFEST, JOURNAL, "../x", "/tmp/x", "frames/x", "x.partial", ""] {
        let e = write_session_file(&sc.dir, bad, b"{}").unwrap_err();
        assert!(matches!(e, SessionError::Refused { .. }), "{bad}: {e}");
    }
    sc.assert_manifest_regular();
}
