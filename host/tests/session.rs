//! The acquisition session on disk: journal round trip, torn and damaged tails, kill-and-resume
//! with real process kills, and the trigger/frame pairing.

use std::collections::{BTreeMap, BTreeSet, HashSet};
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::session::{
    crc32, crc_of_file, decode_line, encode_line, pair, trigger_events, Arrival, Damage, Extra, ExtraReason,
    Manifest, Pair, Pairing, Record, Session, SessionError, SessionIndex, State, StepRecords, Trigger,
    FORMAT_VERSION, JOURNAL, MANIFEST,
};
use lightrig_protocol::event::TriggerEvent;
use lightrig_protocol::Event;

#[path = "support/sessions.rs"]
mod sessions;
use sessions::{event_record, manifest, plan, trigger_event, triggers_of};

// ---------------------------------------------------------------------------------------------
// Helpers

/// A fresh scratch directory. `fast`: on tmpfs where there is one (fsync is free there), for
/// tests that open a session hundreds of times.
fn scratch(name: &str, fast: bool) -> PathBuf {
    static N: AtomicU32 = AtomicU32::new(0);
    let shm = Path::new("/dev/shm");
    let base = if fast && shm.is_dir() { shm.to_path_buf() } else { std::env::temp_dir() };
    let dir = base.join(format!(
        "lightrig-session-{name}-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let _ = fs::remove_dir_all(&dir);
    dir
}

/// Splitmix64: a seeded generator for the tests.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// A frame's image: content and size depend on step, camera and frame only, so a re-acquired
/// step writes the same bytes.
fn image(step: u32, camera: u8, frame: u32) -> Vec<u8> {
    let mut rng = Rng(u64::from(step) << 40 | u64::from(camera) << 32 | u64::from(frame));
    let len = 1024 + rng.below(24 * 1024) as usize;
    (0..len).map(|_| rng.next() as u8).collect()
}

/// Every record of a journal, read without the session code's state machine.
fn raw_records(dir: &Path) -> Vec<Record> {
    let bytes = fs::read(dir.join(JOURNAL)).unwrap();
    bytes
        .split_inclusive(|&b| b == b'\n')
        .map(|line| serde_json::from_slice(decode_line(line).expect("intact line")).unwrap())
        .collect()
}

/// Byte offsets where each journal line starts, and the file length last.
fn line_starts(bytes: &[u8]) -> Vec<usize> {
    let mut starts = vec![0];
    starts.extend(bytes.iter().enumerate().filter(|(_, &b)| b == b'\n').map(|(i, _)| i + 1));
    if starts.last() != Some(&bytes.len()) {
        starts.push(bytes.len());
    }
    starts
}

/// `records` replayed into a fresh state.
fn state_of(records: &[Record], manifest: &Manifest) -> State {
    let mut s = State::default();
    for r in records {
        assert!(s.apply(r, manifest).unwrap());
    }
    s
}

// ---------------------------------------------------------------------------------------------
// 1. Round trip

/// A session with every record kind: step 10 done (a late frame, a missing one, a duplicate),
/// step 11 abandoned once and left open in its second attempt.
fn populated(dir: &Path) -> Session {
    let mut s = Session::create(dir, manifest(plan(3, 2, 3))).unwrap();
    let mut info = virtual_device_info();
    info.boot_id = 0xb007;
    s.device_connected(&info).unwrap();
    let step = s.manifest().plan.steps[0].clone();
    assert_eq!(s.start_step(step.id, 1000).unwrap(), 1);
    let triggers = triggers_of(&step, 1000);
    for (i, t) in triggers.iter().enumerate() {
        assert!(s.record_event(&event_record(0xb007, i as u32, trigger_event(t))).unwrap());
    }
    // A repeated event (after a reconnection) is not journaled twice.
    assert!(!s.record_event(&event_record(0xb007, 3, trigger_event(&triggers[3]))).unwrap());
    let mut arrivals: Vec<Arrival> = triggers
        .iter()
        .filter(|t| (t.camera, t.frame) != (1, 2))
        .map(|t| Arrival { camera: t.camera, frame: Some(t.frame), host_us: t.tick as f64 + 800.0 })
        .collect();
    arrivals[2].host_us += 50_000.0; // late
    arrivals.push(Arrival { camera: 0, frame: Some(0), host_us: 2_000_000.0 }); // duplicate
    let pairing = pair(&triggers, &arrivals, 10_000.0);
    assert_eq!((pairing.pairs.len(), pairing.missing.len(), pairing.extra.len()), (5, 1, 1));
    for p in &pairing.pairs {
        s.store_frame(p, "raw", &image(step.id, p.trigger.camera, p.trigger.frame)).unwrap();
    }
    for t in &pairing.missing {
        s.frame_missing(t, "no frame within 10 ms").unwrap();
    }
    for x in &pairing.extra {
        s.store_extra(x, "raw", b"duplicate frame").unwrap();
    }
    s.record_event(&event_record(
        0xb007,
        6,
        Event::SequenceDone { sequence: 1000, items: 6, tick: 1_006_000 },
    ))
    .unwrap();
    assert_eq!(s.finish_step().unwrap(), (10, 1));
    // Step 11: a fault, then a second attempt left open with one frame.
    let step = s.manifest().plan.steps[1].clone();
    s.start_step(step.id, 1100).unwrap();
    s.abandon_step("device fault: HeartbeatLost").unwrap();
    assert_eq!(s.start_step(step.id, 1101).unwrap(), 2);
    let t = triggers_of(&step, 1101)[0];
    let p = Pair { trigger: t, arrival: 0, arrived_us: 1.0, delay_us: None, late: false };
    s.store_frame(&p, "raw", &image(step.id, 0, 0)).unwrap();
    s
}

#[test]
fn round_trip_rebuilds_the_same_state() {
    let dir = scratch("roundtrip", false);
    let s = populated(&dir);
    let written = s.state().clone();
    let open = s.open_attempt();
    drop(s);

    // Read-only: the same state, nothing dropped, the journal untouched.
    let before = fs::read(dir.join(JOURNAL)).unwrap();
    let (mut r, rec) = Session::read(&dir).unwrap();
    assert_eq!(r.state(), &written);
    assert_eq!((rec.records, rec.dropped_bytes, rec.damage), (written.records, 0, None));
    assert_eq!(rec.interrupted, Some((11, 2)));
    assert!(rec.orphans.is_empty() && rec.bad_files.is_empty() && rec.removed_partials.is_empty());
    assert_eq!(fs::read(dir.join(JOURNAL)).unwrap(), before);
    let refused = r.append(&Record::SessionDone { host_time: String::new() });
    assert!(matches!(refused, Err(SessionError::NotWritable { .. })));
    drop(r);

    // Every record survives JSON unchanged.
    for rec in raw_records(&dir) {
        let json = serde_json::to_vec(&rec).unwrap();
        assert_eq!(serde_json::from_slice::<Record>(&json).unwrap(), rec);
    }

    // Queries.
    let (mut s, recovery) = Session::open(&dir).unwrap();
    assert_eq!(recovery.interrupted, open);
    assert_eq!(recovery.superseded, vec![(11, 1), (11, 2)]);
    assert_eq!(s.steps_done(), BTreeSet::from([10]));
    assert_eq!(s.pending_steps(), vec![11, 12]);
    assert_eq!(s.next_attempt(11), 3);
    assert_eq!(s.next_attempt(12), 1);
    assert_eq!(s.open_attempt(), None);
    let frames = s.frames_of(10);
    assert_eq!(
        frames.iter().map(|f| (f.camera, f.frame)).collect::<Vec<_>>(),
        vec![(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)]
    );
    assert_eq!(frames.iter().filter(|f| f.late).count(), 1);
    assert!(s.frames_of(11).is_empty());
    assert_eq!(s.state().missing_of(10).len(), 1);
    assert_eq!(s.state().extra_of(10)[0].reason, ExtraReason::Duplicate);
    assert_eq!(s.state().events, 7);
    assert!(s.verify().is_empty());
    // The state after opening: the written one, resumed, the open attempt abandoned.
    let mut expected = written.clone();
    expected.records += 2;
    expected.resumes = 1;
    expected.open = None;
    expected.steps.get_mut(&11).unwrap().get_mut(&2).unwrap().outcome =
        lightrig_host::session::Outcome::Abandoned {
            reason: "interrupted: the session stopped before the step was done".into(),
        };
    assert_eq!(s.state(), &expected);

    // The abandoned attempts' directories can go; the completed step's files stay.
    let removed = s.remove_superseded().unwrap();
    assert_eq!(removed, vec![dir.join("frames/step-000011/attempt-02")], "attempt 1 wrote no file");
    assert!(s.verify().is_empty());
    assert!(dir.join("frames/step-000010/attempt-01").is_dir());
    drop(s);
    let (s, _) = Session::read(&dir).unwrap();
    assert_eq!(s.state().resumes, 1);
    fs::remove_dir_all(&dir).unwrap();
}

/// The session's triggers by `(sequence, item)`, from the whole journal.
fn all_triggers(dir: &Path) -> BTreeMap<(u32, u32), TriggerEvent> {
    trigger_events(dir).unwrap().into_iter().collect()
}

/// `SessionIndex::step` against `Session::read`'s state, step by step: the same frames, missing
/// and extra records, each frame's trigger found in the step's own stretch of the journal.
fn index_agrees_with_reading(dir: &Path) {
    let (read, _) = Session::read(dir).unwrap();
    let index = SessionIndex::read(dir).unwrap();
    let triggers = all_triggers(dir);
    assert_eq!(index.is_done(), read.is_done());
    for step in &read.manifest().plan.steps {
        let r = index.step(step.id).unwrap();
        assert_eq!(index.done_attempt(step.id), read.state().done_attempt(step.id).map(|(n, _)| n));
        assert_eq!(r.frames, read.frames_of(step.id), "step {}", step.id);
        assert_eq!(r.missing, read.state().missing_of(step.id));
        assert_eq!(r.extra, read.state().extra_of(step.id));
        for camera in read.cameras() {
            assert_eq!(
                index.frame_count(step.id, camera) as usize,
                read.camera_frames_of(step.id, camera).len()
            );
            assert!(r
                .camera_frames(camera)
                .map(|f| f.frame)
                .eq(read.camera_frames_of(step.id, camera).iter().map(|f| f.frame)));
        }
        for f in &r.frames {
            let t = r.trigger_of(f).unwrap_or_else(|| panic!("{}: no trigger", f.file));
            assert_eq!(Some(t), triggers.get(&(f.sequence, f.item)));
        }
    }
}

#[test]
fn the_index_reads_each_steps_completed_attempt_back_from_the_journal() {
    let dir = scratch("index", true);
    // Step 10 done (a missing frame, a duplicate), step 11 abandoned and then left open.
    drop(populated(&dir));
    index_agrees_with_reading(&dir);
    let index = SessionIndex::read(&dir).unwrap();
    assert_eq!((index.done_attempt(10), index.done_attempt(11)), (Some(1), None));
    assert_eq!(index.step(10).unwrap().frames.len(), 5);
    assert_eq!(index.step(11).unwrap(), StepRecords::default());
    drop(index);

    // Step 10 retaken for its missing frame: attempt 2 is the one read, not attempt 1.
    let (mut s, _) = Session::open(&dir).unwrap();
    assert_eq!(s.reopen_missing().unwrap(), vec![10]);
    acquire_pending(&mut s);
    s.finish().unwrap();
    drop(s);
    index_agrees_with_reading(&dir);
    let index = SessionIndex::read(&dir).unwrap();
    assert!(index.is_done());
    assert_eq!(index.done_attempt(10), Some(2));
    let r = index.step(10).unwrap();
    assert_eq!((r.frames.len(), r.missing.len(), r.extra.len()), (6, 0, 1));
    assert!(r.frames.iter().all(|f| f.attempt == 2 && f.file.starts_with("frames/step-000010/attempt-02/")));

    // A journal cut short after the index was read: the step's records are refused, not half read.
    let journal = dir.join(JOURNAL);
    let bytes = fs::read(&journal).unwrap();
    fs::write(&journal, &bytes[..bytes.len() / 2]).unwrap();
    let last = *index.manifest().plan.steps.iter().map(|p| &p.id).max().unwrap();
    let e = index.step(last).unwrap_err().to_string();
    assert!(e.contains("the journal changed after the session was read"), "{e}");
    fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn records_out_of_order_are_refused_and_nothing_is_written() {
    let dir = scratch("refused", false);
    let mut s = Session::create(&dir, manifest(plan(2, 1, 2))).unwrap();
    let len = fs::metadata(dir.join(JOURNAL)).unwrap().len();
    let refused = |r: Result<_, SessionError>| matches!(r, Err(SessionError::Refused { .. }));
    let t = Trigger { sequence: 1, item: 0, camera: 0, frame: 0, tick: 5, host_us: None };
    let p = Pair { trigger: t, arrival: 0, arrived_us: 0.0, delay_us: None, late: false };
    assert!(refused(s.store_frame(&p, "raw", b"x").map(|_| ())), "no step open");
    assert!(refused(s.start_step(99, 1).map(|_| ())), "not in the plan");
    assert!(refused(s.finish().map(|_| ())), "steps pending");
    s.start_step(10, 1).unwrap();
    assert!(refused(s.start_step(11, 2).map(|_| ())), "one attempt at a time");
    s.store_frame(&p, "raw", b"x").unwrap();
    assert!(refused(s.store_frame(&p, "raw", b"y").map(|_| ())), "frame 0 answered twice");
    assert!(refused(s.frame_missing(&t, "lost").map(|_| ())), "frame 0 answered twice");
    let far = Trigger { frame: 2, ..t };
    assert!(refused(s.frame_missing(&far, "lost").map(|_| ())), "frame 2 is outside the plan");
    assert!(refused(s.finish_step().map(|_| ())), "frame 1 unanswered");
    assert!(refused(
        s.store_frame(&Pair { trigger: Trigger { frame: 1, ..t }, ..p }, "RAW", b"x").map(|_| ())
    ));
    s.frame_missing(&Trigger { frame: 1, ..t }, "lost").unwrap();
    s.finish_step().unwrap();
    assert!(refused(s.start_step(10, 3).map(|_| ())), "step 10 is done");
    // Only the accepted records are in the journal.
    let kinds: Vec<&str> = raw_records(&dir).iter().map(|r| r.kind()).collect();
    assert_eq!(kinds, ["SessionStarted", "StepStarted", "Frame", "FrameMissing", "StepDone"]);
    assert!(fs::metadata(dir.join(JOURNAL)).unwrap().len() > len);
    // No file was written for a refused frame.
    let files: Vec<_> = fs::read_dir(dir.join("frames/step-000010/attempt-01")).unwrap().collect();
    assert_eq!(files.len(), 1);
    // One writer at a time; readers are welcome.
    let busy = Session::open(&dir).map(|_| ());
    assert!(matches!(busy, Err(SessionError::Busy { .. })), "{busy:?}");
    assert!(Session::read(&dir).is_ok());
    // A second create in the same directory is refused.
    drop(s);
    assert!(matches!(Session::create(&dir, manifest(plan(1, 1, 1))), Err(SessionError::Exists { .. })));
    fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------------------------------
// 2. Torn and damaged tails

#[test]
fn a_torn_tail_at_any_byte_is_dropped_exactly() {
    let dir = scratch("torn", true);
    drop(populated(&dir));
    let journal = dir.join(JOURNAL);
    let full = fs::read(&journal).unwrap();
    let records = raw_records(&dir);
    let m: Manifest = serde_json::from_slice(&fs::read(dir.join(MANIFEST)).unwrap()).unwrap();
    let starts = line_starts(&full);
    let lines = starts.len() - 1;
    assert_eq!(lines, records.len());
    // Every cut inside the last 4 records (and at their ends).
    let from = starts[lines - 4];
    for cut in from..=full.len() {
        let kept = starts.iter().rposition(|&s| s <= cut).unwrap();
        let good = starts[kept];
        fs::write(&journal, &full[..cut]).unwrap();

        let (r, rec) = Session::read(&dir).unwrap();
        assert_eq!(rec.records, kept as u64, "cut {cut}");
        assert_eq!(rec.dropped_bytes, (cut - good) as u64, "cut {cut}");
        assert_eq!(rec.damage, (cut > good).then_some(Damage::Torn), "cut {cut}");
        assert_eq!(r.state(), &state_of(&records[..kept], &m), "cut {cut}");
        drop(r);

        let (mut s, rec) = Session::open(&dir).unwrap();
        assert_eq!((rec.records, rec.dropped_bytes), (kept as u64, (cut - good) as u64), "cut {cut}");
        let after = fs::read(&journal).unwrap();
        assert_eq!(&after[..good], &full[..good], "cut {cut}: the intact records stay byte for byte");
        if cut > good {
            let saved = rec.saved_to.clone().unwrap();
            assert_eq!(fs::read(&saved).unwrap(), &full[good..cut], "cut {cut}: the dropped bytes are kept");
            fs::remove_file(saved).unwrap();
        }
        // Appending after the recovery works, and the result reads back whole.
        s.record_event(&event_record(0xdead, 0, Event::Marker { sequence: 0, item: 0, id: 7, tick: 1 }))
            .unwrap();
        let appended = s.state().records;
        drop(s);
        let (r, rec) = Session::read(&dir).unwrap();
        assert_eq!((rec.records, rec.dropped_bytes), (appended, 0), "cut {cut}");
        assert_eq!(r.state().resumes, 1);
    }
    fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_damaged_byte_drops_that_record_and_everything_after() {
    let dir = scratch("flip", true);
    drop(populated(&dir));
    let journal = dir.join(JOURNAL);
    let full = fs::read(&journal).unwrap();
    let records = raw_records(&dir);
    let m: Manifest = serde_json::from_slice(&fs::read(dir.join(MANIFEST)).unwrap()).unwrap();
    let starts = line_starts(&full);
    let lines = starts.len() - 1;
    let mut rng = Rng(42);
    for line in lines - 4..lines {
        // The CRC digits, the tab, the JSON and the line feed: 12 bytes of each line at random,
        // and its first and last.
        let (a, b) = (starts[line], starts[line + 1]);
        let mut at: Vec<usize> = (0..12).map(|_| a + rng.below((b - a) as u64) as usize).collect();
        at.extend([a, a + 8, b - 1]);
        for pos in at {
            for flip in [0xff_u8, 0x20, 0x01] {
                let mut bad = full.clone();
                bad[pos] ^= flip;
                fs::write(&journal, &bad).unwrap();
                let what = format!("line {line} byte {pos} ^ {flip:#x}");
                let (r, rec) = Session::read(&dir).unwrap();
                assert_eq!(rec.records, line as u64, "{what}");
                assert_eq!(rec.dropped_bytes, (full.len() - a) as u64, "{what}");
                assert!(rec.damage.is_some(), "{what}");
                // Damage before intact lines is told apart from a torn end.
                let after = lines - line - 1;
                assert!(rec.intact_after <= after && rec.intact_after + 1 >= after, "{what}");
                assert_eq!(r.state(), &state_of(&records[..line], &m), "{what}");
                drop(r);
                // Damage with intact lines after it is not a crash's torn write: opening to go
                // on refuses, naming the line, and changes nothing, unless told to drop it.
                let (mut s, rec) = if rec.intact_after > 0 {
                    let e = Session::open(&dir).unwrap_err();
                    assert!(
                        matches!(e, SessionError::Damaged { line: l, .. } if l == line as u64 + 1),
                        "{what}: {e}"
                    );
                    assert!(e.to_string().contains("--drop-damaged-tail"), "{e}");
                    assert_eq!(fs::read(&journal).unwrap(), bad, "{what}: nothing changed");
                    Session::open_dropping_damage(&dir).unwrap()
                } else {
                    Session::open(&dir).unwrap()
                };
                assert_eq!(
                    (rec.records, rec.dropped_bytes),
                    (line as u64, (full.len() - a) as u64),
                    "{what}"
                );
                assert_eq!(&fs::read(&journal).unwrap()[..a], &full[..a], "{what}");
                s.device_connected(&virtual_device_info()).unwrap();
                drop(s);
                assert_eq!(Session::read(&dir).unwrap().1.dropped_bytes, 0, "{what}");
                fs::remove_file(rec.saved_to.unwrap()).unwrap();
            }
        }
    }
    fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_intact_line_that_breaks_the_history_is_an_error_not_a_truncation() {
    let dir = scratch("history", false);
    drop(populated(&dir));
    let journal = dir.join(JOURNAL);
    let mut bytes = fs::read(&journal).unwrap();
    let before = bytes.len();
    // A second StepStarted for the done step, with a valid CRC.
    let payload = br#"{"type":"StepStarted","step":10,"attempt":2,"sequence_id":5,"host_time":"x"}"#;
    bytes.extend(encode_line(payload));
    fs::write(&journal, &bytes).unwrap();
    let e = Session::open(&dir).unwrap_err();
    assert!(matches!(e, SessionError::Corrupt { .. }), "{e}");
    assert!(e.to_string().contains("not a torn write"), "{e}");
    assert_eq!(fs::read(&journal).unwrap().len(), before + payload.len() + 10, "nothing truncated");
    fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_line_format_is_the_documented_one() {
    // The example of docs/session-format.md, "Journal lines".
    let payload = br#"{"type":"SessionDone","host_time":"2025-03-01T12:00:00.000Z"}"#;
    let line = encode_line(payload);
    assert_eq!(crc32(b"123456789"), 0xcbf4_3926, "the CRC-32/ISO-HDLC check value");
    assert_eq!(
        String::from_utf8(line.clone()).unwrap(),
        format!("{:08x}\t{}\n", crc32(payload), std::str::from_utf8(payload).unwrap())
    );
    assert_eq!(&line[..9], b"baf818dc\t");
    assert_eq!(decode_line(&line), Ok(&payload[..]));
    assert_eq!(decode_line(&line[..line.len() - 1]), Err(Damage::Torn));
    let mut upper = line.clone();
    upper[..8].make_ascii_uppercase();
    assert_eq!(decode_line(&upper), Err(Damage::BadPrefix), "lowercase hex only");
    let rec: Record = serde_json::from_slice(payload).unwrap();
    assert_eq!(rec, Record::SessionDone { host_time: "2025-03-01T12:00:00.000Z".into() });
}

#[test]
fn the_examples_in_the_format_doc_parse() {
    let doc = include_str!("../../docs/session-format.md");
    let (mut records, mut manifests, mut lines) = (0, 0, 0);
    for block in doc.split("```").skip(1).step_by(2) {
        let (lang, body) = block.split_once('\n').unwrap();
        match lang {
            "json" if body.contains("\"session_id\"") && body.contains("\"plan\"") => {
                let m: Manifest = serde_json::from_str(body).unwrap();
                assert_eq!(m.plan.steps.len(), 2);
                manifests += 1;
            }
            "json" => {
                let r: Record = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {body}"));
                // Every field of the example is one the record has (nothing misspelt).
                let back = serde_json::to_value(&r).unwrap();
                let given: serde_json::Value = serde_json::from_str(body).unwrap();
                assert_eq!(back, given, "{body}");
                records += 1;
            }
            "jsonl" => {
                for line in body.split_inclusive('\n') {
                    let payload = decode_line(line.as_bytes()).unwrap_or_else(|e| panic!("{e:?}: {line}"));
                    serde_json::from_slice::<Record>(payload).unwrap();
                    lines += 1;
                }
            }
            _ => {}
        }
    }
    assert_eq!((manifests, records, lines), (1, 15, 4));
}

#[test]
fn going_on_with_an_older_hosts_session_raises_its_format_and_reading_it_does_not() {
    let dir = scratch("older", false);
    drop(Session::create(&dir, manifest(plan(1, 1, 1))).unwrap());
    let path = dir.join("manifest.json");
    let mut m: serde_json::Value = serde_json::from_slice(&fs::read(&path).unwrap()).unwrap();
    m["format"] = 2.into();
    fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let format =
        || serde_json::from_slice::<serde_json::Value>(&fs::read(&path).unwrap()).unwrap()["format"].clone();
    drop(Session::read(&dir).unwrap());
    assert_eq!(format(), 2, "reading changes nothing");
    let (s, _) = Session::open(&dir).unwrap();
    assert_eq!(format(), FORMAT_VERSION, "the journal may now hold this format's records");
    assert_eq!(s.manifest().format, FORMAT_VERSION);
    drop(s);
    fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------------------------------
// 3. Kill and resume

const KILL_STEPS: u32 = 5;
const KILL_CAMERAS: u8 = 2;
const KILL_FRAMES: u32 = 4;
/// The simulated device: one run of it across all host restarts.
const BOOT: u32 = 0x0b00_7001;

/// One host run of a simulated acquisition: opens (or creates) the session and acquires every
/// pending step. The frame source delivers every frame, plus a duplicate of each step's first.
fn acquire(dir: &Path) {
    let (mut s, _) =
        Session::open_or_create(dir, manifest(plan(KILL_STEPS, KILL_CAMERAS, KILL_FRAMES))).unwrap();
    if s.is_done() {
        return;
    }
    acquire_pending(&mut s);
    s.finish().unwrap();
}

/// Acquires each of `s`'s pending steps, as device `BOOT`: every frame, plus a duplicate of each
/// step's first.
fn acquire_pending(s: &mut Session) {
    let mut info = virtual_device_info();
    info.boot_id = BOOT;
    s.device_connected(&info).unwrap();
    // The device goes on numbering its events; after a reconnection it resends the last few the
    // host had not acknowledged.
    let mut index = s.state().last_event.get(&BOOT).map_or(0, |last| last.saturating_sub(2));
    let mut event = |s: &mut Session, e: Event| {
        s.record_event(&event_record(BOOT, index, e)).unwrap();
        index += 1;
    };
    for id in s.pending_steps() {
        let step = s.manifest().step(id).unwrap().clone();
        let sequence = id * 100 + s.next_attempt(id);
        s.start_step(id, sequence).unwrap();
        let triggers = triggers_of(&step, sequence);
        let mut arrivals = Vec::new();
        for t in &triggers {
            event(s, trigger_event(t));
            arrivals.push(Arrival { camera: t.camera, frame: Some(t.frame), host_us: t.tick as f64 + 900.0 });
        }
        arrivals.push(arrivals[0]);
        event(s, Event::SequenceDone { sequence, items: triggers.len() as u32, tick: 2_000_000 });
        let pairing = pair(&triggers, &arrivals, 5_000.0);
        for p in &pairing.pairs {
            s.store_frame(p, "raw", &image(id, p.trigger.camera, p.trigger.frame)).unwrap();
        }
        for x in &pairing.extra {
            s.store_extra(x, "raw", &image(id, x.camera, x.frame)).unwrap();
        }
        s.finish_step().unwrap();
    }
}

/// The child side of `kill_and_resume_loses_and_duplicates_nothing`: runs only when re-executed
/// with `LIGHTRIG_SESSION_CHILD` set.
#[test]
fn kill_child() {
    if let Some(dir) = std::env::var_os("LIGHTRIG_SESSION_CHILD") {
        acquire(Path::new(&dir));
    }
}

fn spawn_child(dir: &Path) -> std::process::Child {
    Command::new(std::env::current_exe().unwrap())
        .args(["kill_child", "--exact", "--test-threads=1", "--nocapture"])
        .env("LIGHTRIG_SESSION_CHILD", dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// Checks a finished session from the raw journal, without the session's state machine: every
/// planned frame exactly once in its step's completed attempt, every file whole.
fn check_complete(dir: &Path) {
    let records = raw_records(dir);
    let mut done: BTreeMap<u32, u32> = BTreeMap::new();
    for r in &records {
        if let Record::StepDone { step, attempt, .. } = r {
            assert!(done.insert(*step, *attempt).is_none(), "step {step} done twice");
        }
    }
    assert_eq!(done.len() as u32, KILL_STEPS);
    assert!(matches!(records.last(), Some(Record::SessionDone { .. })));
    let mut seen = HashSet::new();
    let mut events = HashSet::new();
    for r in &records {
        match r {
            Record::Frame(f) if done.get(&f.step) == Some(&f.attempt) => {
                assert!(seen.insert((f.step, f.camera, f.frame)), "duplicate {f:?}");
                let path = dir.join(&f.file);
                assert_eq!(fs::metadata(&path).unwrap().len(), f.bytes);
                assert_eq!(crc_of_file(&path).unwrap(), f.crc32);
                assert_eq!(fs::read(&path).unwrap(), image(f.step, f.camera, f.frame));
            }
            Record::Event { boot_id, index, .. } => assert!(events.insert((*boot_id, *index)), "event twice"),
            _ => {}
        }
    }
    let planned: HashSet<_> = (0..KILL_STEPS)
        .flat_map(|s| (0..KILL_CAMERAS).flat_map(move |c| (0..KILL_FRAMES).map(move |f| (10 + s, c, f))))
        .collect();
    assert_eq!(seen, planned);
    // ... and the session's own view agrees.
    let (s, rec) = Session::read(dir).unwrap();
    assert!(s.is_done() && s.pending_steps().is_empty());
    assert_eq!(rec.dropped_bytes, 0);
    assert!(rec.bad_files.is_empty() && s.verify().is_empty());
    assert_eq!(s.frame_index().len(), planned.len());
}

/// Runs a child acquisition on `dir` and kills it (SIGKILL) once the journal has grown past a
/// random length, a random few hundred microseconds later; whether it was killed (rather than
/// finished first).
fn run_and_kill(dir: &Path, rng: &mut Rng, full_len: u64) -> bool {
    let journal = dir.join(JOURNAL);
    let len = || fs::metadata(&journal).map_or(0, |m| m.len());
    let now = len();
    let target = now + rng.below(full_len.saturating_sub(now).max(1));
    let jitter = Duration::from_micros(rng.below(1000));
    let mut child = spawn_child(dir);
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if child.try_wait().unwrap().is_some() {
            return false;
        }
        if len() >= target || Instant::now() > deadline {
            std::thread::sleep(jitter);
            child.kill().unwrap(); // SIGKILL
            return !child.wait().unwrap().success();
        }
        std::thread::sleep(Duration::from_micros(100));
    }
}

#[test]
fn kill_and_resume_loses_and_duplicates_nothing() {
    let t0 = Instant::now();
    // An uninterrupted run, for the journal's full length.
    let dir = scratch("kill-full", false);
    assert!(spawn_child(&dir).wait().unwrap().success());
    check_complete(&dir);
    let full_len = fs::metadata(dir.join(JOURNAL)).unwrap().len();
    fs::remove_dir_all(&dir).unwrap();

    let mut rng = Rng(0x5eed_1e55);
    let (mut kills, mut resumed_steps) = (0, 0);
    // Kills inside a step, partial files, orphan files, torn journal ends.
    let mut seen = [0usize; 4];
    for _ in 0..10 {
        let dir = scratch("kill", false);
        for _ in 0..3 {
            kills += usize::from(run_and_kill(&dir, &mut rng, full_len));
            // What the next run will find (reading changes nothing).
            if let Ok((_, r)) = Session::read(&dir) {
                seen[0] += usize::from(r.interrupted.is_some());
                seen[1] += r.removed_partials.len();
                seen[2] += r.orphans.len();
                seen[3] += usize::from(r.dropped_bytes > 0);
            }
        }
        let before = Session::read(&dir).map(|(s, _)| s.steps_done().len()).unwrap_or(0);
        acquire(&dir);
        resumed_steps += KILL_STEPS as usize - before;
        check_complete(&dir);
        fs::remove_dir_all(&dir).unwrap();
    }
    assert!(kills >= 20, "only {kills} of 30 children were killed before they finished");
    assert!(resumed_steps > 0);
    assert!(seen[0] >= 10, "kills inside a step: {}", seen[0]);
    eprintln!(
        "kill-and-resume: {kills} kills ({} inside a step; {} partial files, {} orphans, {} torn ends \
         found), {resumed_steps} steps left to the last run, {:?}",
        seen[0],
        seen[1],
        seen[2],
        seen[3],
        t0.elapsed()
    );
}
// ---------------------------------------------------------------------------------------------
// 4. Pairing

fn trig(camera: u8, frame: u32, item: u32, host_us: Option<f64>) -> Trigger {
    Trigger { sequence: 7, item, camera, frame, tick: 1000 * u64::from(item), host_us }
}

#[test]
fn pairing_finds_missing_duplicate_late_and_extra_frames() {
    let t = [
        trig(0, 0, 0, Some(1000.0)),
        trig(1, 0, 1, Some(1100.0)),
        trig(0, 1, 2, Some(2000.0)),
        trig(1, 1, 3, Some(2100.0)),
        trig(0, 2, 4, Some(3000.0)),
        trig(1, 2, 5, None),
    ];
    let a = [
        Arrival { camera: 0, frame: Some(0), host_us: 1400.0 }, // on time
        Arrival { camera: 1, frame: None, host_us: 1500.0 },    // camera 1 by order: 0
        Arrival { camera: 0, frame: Some(1), host_us: 9000.0 }, // 7000 after: late
        Arrival { camera: 0, frame: Some(0), host_us: 9100.0 }, // second frame 0: duplicate
        Arrival { camera: 1, frame: None, host_us: 2600.0 },    // camera 1 by order: 1
        Arrival { camera: 0, frame: Some(5), host_us: 9500.0 }, // no such trigger
        Arrival { camera: 3, frame: Some(0), host_us: 9600.0 }, // camera without triggers
        Arrival { camera: 1, frame: None, host_us: 1e9 },       // order 2: no host time, never late
        Arrival { camera: 1, frame: None, host_us: 1e9 + 1.0 }, // order 3: no trigger
    ];
    let p = pair(&t, &a, 5000.0);
    let pr = |trigger: Trigger, arrival: usize, late: bool| Pair {
        trigger,
        arrival,
        arrived_us: a[arrival].host_us,
        delay_us: trigger.host_us.map(|h| a[arrival].host_us - h),
        late,
    };
    let ex = |arrival: usize, frame: u32, reason: ExtraReason| Extra {
        arrival,
        camera: a[arrival].camera,
        frame,
        arrived_us: a[arrival].host_us,
        reason,
    };
    let expected = Pairing {
        pairs: vec![
            pr(t[0], 0, false),
            pr(t[1], 1, false),
            pr(t[2], 2, true),
            pr(t[3], 4, false),
            pr(t[5], 7, false),
        ],
        missing: vec![t[4]],
        extra: vec![
            ex(3, 0, ExtraReason::Duplicate),
            ex(5, 5, ExtraReason::NoTrigger),
            ex(6, 0, ExtraReason::NoTrigger),
            ex(8, 3, ExtraReason::NoTrigger),
        ],
    };
    assert_eq!(p, expected);
    assert_eq!(p.late().map(|x| x.trigger.item).collect::<Vec<_>>(), vec![2]);
    assert_eq!(p.pairs[2].delay_us, Some(7000.0));
    // Exactly at the tolerance is not late.
    let edge = pair(&t[..1], &[Arrival { camera: 0, frame: Some(0), host_us: 6000.0 }], 5000.0);
    assert!(!edge.pairs[0].late);
}

#[test]
fn pairing_edge_cases() {
    // Nothing arrived: all missing. Nothing triggered: all extra.
    let t = [trig(0, 0, 0, Some(0.0)), trig(0, 1, 1, Some(1.0))];
    let p = pair(&t, &[], 10.0);
    assert_eq!((p.pairs.len(), p.missing, p.extra.len()), (0, t.to_vec(), 0));
    let a = [Arrival { camera: 0, frame: Some(0), host_us: 0.0 }];
    let p = pair(&[], &a, 10.0);
    assert_eq!(
        p.extra,
        vec![Extra { arrival: 0, camera: 0, frame: 0, arrived_us: 0.0, reason: ExtraReason::NoTrigger }]
    );
    // Frames out of order still pair by number; a repeated trigger is ignored.
    let a = [
        Arrival { camera: 0, frame: Some(1), host_us: 5.0 },
        Arrival { camera: 0, frame: Some(0), host_us: 6.0 },
    ];
    let p = pair(&[t[0], t[1], t[0]], &a, 10.0);
    assert_eq!(
        p.pairs.iter().map(|p| (p.trigger.frame, p.arrival)).collect::<Vec<_>>(),
        vec![(0, 1), (1, 0)]
    );
    assert!(p.missing.is_empty() && p.extra.is_empty());
    // From a client event record.
    let e = event_record(1, 2, trigger_event(&t[1]));
    assert_eq!(Trigger::from_record(&e), Some(Trigger { host_us: Some(1000.25), ..t[1] }));
}

#[test]
fn a_session_refuses_links_and_frame_paths_that_lead_out_of_it() {
    // A journal that is a symbolic link (to another session's, say) is refused and untouched.
    let dir = scratch("links", true);
    drop(populated(&dir));
    let elsewhere = dir.with_extension("elsewhere");
    let _ = fs::remove_dir_all(&elsewhere);
    fs::create_dir_all(&elsewhere).unwrap();
    let real = elsewhere.join(JOURNAL);
    fs::rename(dir.join(JOURNAL), &real).unwrap();
    std::os::unix::fs::symlink(&real, dir.join(JOURNAL)).unwrap();
    let before = fs::read(&real).unwrap();
    for e in [Session::open(&dir).map(|_| ()).unwrap_err(), Session::read(&dir).map(|_| ()).unwrap_err()] {
        assert!(matches!(e, SessionError::Foreign { .. }), "{e}");
        assert!(e.to_string().contains("symbolic link"), "{e}");
    }
    assert_eq!(fs::read(&real).unwrap(), before, "the linked journal untouched");
    fs::remove_file(dir.join(JOURNAL)).unwrap();
    fs::rename(&real, dir.join(JOURNAL)).unwrap();
    // A link inside frames/ too.
    std::os::unix::fs::symlink(&elsewhere, dir.join("frames").join("step-999999")).unwrap();
    let e = Session::open(&dir).map(|_| ()).unwrap_err();
    assert!(matches!(e, SessionError::Foreign { .. }), "{e}");
    fs::remove_file(dir.join("frames").join("step-999999")).unwrap();
    assert!(Session::read(&dir).is_ok());
    // A Frame record (with an intact CRC) naming a file outside its attempt's folder.
    let journal = dir.join(JOURNAL);
    let good = fs::read(&journal).unwrap();
    for file in ["/etc/passwd", "frames/step-000010/attempt-01/../../../x", "../x", "frames/x.raw"] {
        // Attempt 2 of step 11 is open (`populated`); camera 1's frame 0 is not answered yet.
        let mut bytes = good.clone();
        let frame = format!(
            r#"{{"type":"Frame","step":11,"attempt":2,"camera":1,"frame":0,"sequence":1101,"item":0,"tick":1,"trigger_us":null,"arrived_us":1.0,"late":false,"file":{file:?},"bytes":1,"crc32":"00000000"}}"#
        );
        bytes.extend(encode_line(frame.as_bytes()));
        fs::write(&journal, &bytes).unwrap();
        let e = Session::read(&dir).map(|_| ()).unwrap_err();
        assert!(matches!(e, SessionError::Corrupt { .. }), "{file}: {e}");
        assert!(e.to_string().contains("is not a file of its attempt's folder"), "{file}: {e}");
    }
    fs::write(&journal, &good).unwrap();
    fs::remove_dir_all(&dir).unwrap();
    fs::remove_dir_all(&elsewhere).unwrap();
}

#[test]
fn a_tap_hears_every_record_this_process_writes_as_its_journal_line_says() {
    let dir = scratch("tap", true);
    let mut s = Session::create(&dir, manifest(plan(2, 1, 2))).unwrap();
    let heard = std::sync::Arc::new(std::sync::Mutex::new(Vec::<Vec<u8>>::new()));
    let h = heard.clone();
    // Set after the session was created: SessionStarted is heard first all the same.
    s.set_tap(Some(std::sync::Arc::new(move |json: &[u8]| h.lock().unwrap().push(json.to_vec()))));
    let mut info = virtual_device_info();
    info.boot_id = 7;
    s.device_connected(&info).unwrap();
    let step = s.manifest().plan.steps[0].clone();
    let step_id = step.id;
    s.start_step(step.id, 1000).unwrap();
    let triggers = triggers_of(&step, 1000);
    assert!(s.record_event(&event_record(7, 0, trigger_event(&triggers[0]))).unwrap());
    // Refused or repeated records are not written, and not heard.
    assert!(!s.record_event(&event_record(7, 0, trigger_event(&triggers[0]))).unwrap());
    drop(s);
    let text = fs::read(dir.join(JOURNAL)).unwrap();
    let lines: Vec<Vec<u8>> =
        text.split_inclusive(|&b| b == b'\n').map(|l| decode_line(l).unwrap().to_vec()).collect();
    assert_eq!(*heard.lock().unwrap(), lines, "heard byte for byte as journaled");
    assert_eq!(lines.len(), 4);

    // A resumed session: its Resumed record first, nothing of the earlier process's.
    let (mut s, _) = Session::open(&dir).unwrap();
    let again = std::sync::Arc::new(std::sync::Mutex::new(Vec::<Vec<u8>>::new()));
    let a = again.clone();
    s.set_tap(Some(std::sync::Arc::new(move |json: &[u8]| a.lock().unwrap().push(json.to_vec()))));
    let heard: Vec<Record> =
        again.lock().unwrap().iter().map(|j| serde_json::from_slice(j).unwrap()).collect();
    // Opening closed the step the first process left open: heard too.
    assert!(
        matches!(heard.as_slice(), [Record::Resumed { attempt: 1, .. }, Record::StepAbandoned { step, .. }] if *step == step_id),
        "{heard:?}"
    );
}
