//! The acquisition session on disk: a journal written as the session runs, the frame files,
//! and resuming after a crash or an unplug with no frame lost and none duplicated.
//!
//! A session directory holds `manifest.json` (written once), `journal.jsonl` (append-only, one
//! CRC-checked record per line, the source of truth) and `frames/` (the image files). The
//! format is specified in `docs/session-format.md`.
//!
//! ```text
//! let (mut s, recovery) = Session::open_or_create(dir, manifest)?;
//! for step in s.pending_steps() {
//!     let attempt = s.start_step(step, sequence_id)?;      // synced
//!     // run the sequence; journal events with s.record_event(&e)?
//!     let pairing = pair(&triggers, &arrivals, tolerance_us);
//!     for p in &pairing.pairs { s.store_frame(p, "raw", &image)?; }   // file, then record
//!     for t in &pairing.missing { s.frame_missing(t, "no frame")?; }
//!     for x in &pairing.extra { s.store_extra(x, "raw", &image)?; }
//!     s.finish_step()?;                                      // synced
//! }
//! s.finish()?;
//! ```
//!
//! A step is atomic: an attempt that did not reach `StepDone` is abandoned when the session is
//! opened again, and the step is acquired anew as the next attempt.

mod fsutil;
mod index;
mod journal;
mod pairing;
mod reader;
mod records;
mod state;
mod syncer;

use std::collections::HashSet;
use std::fmt;
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use lightrig_protocol::event::FaultCause;
use lightrig_protocol::session::DeviceInfo;

use crate::client::EventRecord;

pub use fsutil::{now_rfc3339, rfc3339};
pub use index::{SessionIndex, StepRecords};
pub use journal::{crc32, decode_line, encode_line, Crc32, Damage};
pub use pairing::{camera_clock, off_their_triggers, pair, repair_by_stamps, Arrival, CameraClock, Extra};
pub use pairing::{ExtraReason, Pair, Pairing, RobustClock, Trigger};
pub use reader::{Frames, ReadFrame};
pub use records::{
    new_session_id, CameraStamp, CameraTriggers, DeviceSummary, ExtraRecord, FrameRecord, Manifest,
    MissingRecord, PlanStep, PlanSummary, Record, StepId,
};
pub use state::{Attempt, Outcome, State};

/// Version of the session format this host writes (and the newest it reads). 2 added the
/// `StepPrepared` record, 3 `FaultCleared`, 4 `StepReopened`.
pub const FORMAT_VERSION: u32 = 4;
/// The manifest's file name.
pub const MANIFEST: &str = "manifest.json";
/// The journal's file name.
pub const JOURNAL: &str = "journal.jsonl";
/// The frame files' directory.
pub const FRAMES: &str = "frames";
/// Suffix of a file being written; never named by a record, removed when the session is opened.
pub const PARTIAL_SUFFIX: &str = ".partial";

/// What went wrong with a session directory. Each message says what, where and what to do.
#[derive(Debug)]
pub enum SessionError {
    /// A file operation failed.
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The error.
        error: io::Error,
    },
    /// The directory has no `manifest.json`.
    NotASession {
        /// The directory.
        dir: PathBuf,
    },
    /// `create` found a directory that is not empty.
    Exists {
        /// The directory.
        dir: PathBuf,
    },
    /// The manifest or a committed journal record cannot be read or does not fit the history
    /// before it. Not a torn write (those are dropped): the files were changed by something else.
    Corrupt {
        /// The file.
        path: PathBuf,
        /// Line number (1-based) in the journal, 0 for the manifest.
        line: usize,
        /// What is wrong.
        detail: String,
    },
    /// The session was written by a newer lightrig.
    Newer {
        /// The directory.
        dir: PathBuf,
        /// Its format version.
        format: u32,
    },
    /// Another process (or another `Session` in this one) has the session open for writing.
    Busy {
        /// The directory.
        dir: PathBuf,
    },
    /// The record does not fit the session's state; nothing was written.
    Refused {
        /// Why.
        detail: String,
    },
    /// The session was opened read-only, or an earlier write failed (the journal's end is then
    /// unknown: open the session again to recover).
    NotWritable {
        /// Why.
        detail: String,
    },
    /// Something in the session directory does not belong in one, where the session reads or
    /// writes its own files: a symbolic link (never followed to write), a journal with a second
    /// name (a hard link), a file that is not a regular one, a file where a folder must be.
    /// Nothing was written through it.
    Foreign {
        /// The path.
        path: PathBuf,
        /// What is wrong, and what to do.
        detail: String,
    },
    /// The journal is damaged inside, with intact records after the damage: not a torn write
    /// at a crash, so it is not dropped without being asked to
    /// ([`Session::open_dropping_damage`]).
    Damaged {
        /// The journal.
        path: PathBuf,
        /// Line (1-based) of the first damaged record.
        line: u64,
        /// Bytes from there to the end.
        bytes: u64,
        /// Intact-looking lines among them.
        intact_after: usize,
    },
}

impl fmt::Display for SessionError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SessionError::Io { path, error } => write!(f, "{}: {error}", path.display()),
            SessionError::NotASession { dir } => write!(
                f,
                "{}: not a lightrig session (no {MANIFEST}); create one, or give the session's directory",
                dir.display()
            ),
            SessionError::Exists { dir } => write!(
                f,
                "{}: the directory is not empty; a new session needs a new (or empty) directory, an \
                 interrupted one is resumed with open",
                dir.display()
            ),
            SessionError::Corrupt { path, line: 0, detail } => write!(f, "{}: {detail}", path.display()),
            SessionError::Corrupt { path, line, detail } => write!(
                f,
                "{} line {line}: {detail}; the line's CRC is intact, so this is not a torn write: the \
                 journal was edited or written by other software",
                path.display()
            ),
            SessionError::Newer { dir, format } => write!(
                f,
                "{}: session format {format}, this host reads up to {FORMAT_VERSION}; use a newer lightrig",
                dir.display()
            ),
            SessionError::Busy { dir } => write!(
                f,
                "{}: another lightrig process is writing this session; stop it first (reading with \
                 Session::read is fine meanwhile)",
                dir.display()
            ),
            SessionError::Refused { detail } => write!(f, "record refused: {detail}"),
            SessionError::NotWritable { detail } => write!(f, "session not writable: {detail}"),
            SessionError::Foreign { path, detail } => write!(f, "{}: {detail}", path.display()),
            SessionError::Damaged { path, line, bytes, intact_after } => write!(
                f,
                "{} line {line}: damaged, and {intact_after} intact-looking line(s) follow in the {bytes} bytes from \
                 there: not a torn write at a crash. Look at it first; `lightrig resume --drop-damaged-tail` goes \
                 on from line {line}, keeping the dropped bytes in {JOURNAL}.dropped.N beside the journal",
                path.display()
            ),
        }
    }
}

impl std::error::Error for SessionError {}

/// Result of session operations.
pub type Result<T, E = SessionError> = std::result::Result<T, E>;

fn io_at(path: &Path) -> impl Fn(io::Error) -> SessionError + '_ {
    move |error| SessionError::Io { path: path.to_path_buf(), error }
}

/// When the journal is fsynced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SyncPolicy {
    /// After an `Event` record, an fsync is started on the session's own thread if the last
    /// one is at least this old (the caller, the link loop, never waits on the disk); every
    /// other record is fsynced before `append` returns.
    pub event_interval: Duration,
}

impl Default for SyncPolicy {
    fn default() -> Self {
        SyncPolicy { event_interval: Duration::from_millis(100) }
    }
}

/// A frame file's problem, found when opening or by [`Session::verify`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileProblem {
    /// The file, relative to the session directory.
    pub file: String,
    /// What is wrong.
    pub problem: String,
}

/// What opening a session found and did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Recovery {
    /// Intact records read.
    pub records: u64,
    /// Bytes dropped from the journal's end (a torn write or damage), 0 if none.
    pub dropped_bytes: u64,
    /// What the first dropped line had wrong.
    pub damage: Option<Damage>,
    /// Intact-looking lines among the dropped ones: more than 0 means damage inside the file,
    /// not a torn end.
    pub intact_after: usize,
    /// Where the dropped bytes were saved (`journal.jsonl.dropped.N`), if any were dropped.
    pub saved_to: Option<PathBuf>,
    /// The attempt that was open when the session stopped (now abandoned).
    pub interrupted: Option<(StepId, u32)>,
    /// Every abandoned attempt: its records and files are superseded.
    pub superseded: Vec<(StepId, u32)>,
    /// Partly written frame files removed (relative paths).
    pub removed_partials: Vec<String>,
    /// Complete frame files no record names (written just before a stop, or by something
    /// else); left in place, not part of the session.
    pub orphans: Vec<String>,
    /// Files of completed attempts that are missing or have the wrong size.
    pub bad_files: Vec<FileProblem>,
}

/// In words, for a person resuming the session.
impl fmt::Display for Recovery {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} journal records read", self.records)?;
        if self.dropped_bytes > 0 {
            write!(f, "; {} bytes dropped from the journal's end", self.dropped_bytes)?;
            if let Some(d) = self.damage {
                write!(f, " ({})", d.describe())?;
            }
            if self.intact_after > 0 {
                write!(
                    f,
                    ", {} intact-looking lines among them (damage inside the file)",
                    self.intact_after
                )?;
            }
            if let Some(p) = &self.saved_to {
                write!(f, ", kept in {}", p.display())?;
            }
        }
        if let Some((step, attempt)) = self.interrupted {
            write!(f, "; step {step} (attempt {attempt}) was cut short: it is acquired again")?;
        }
        if !self.removed_partials.is_empty() {
            write!(f, "; {} partly written frame file(s) removed", self.removed_partials.len())?;
        }
        if !self.orphans.is_empty() {
            write!(f, "; {} frame file(s) no record names, left in place", self.orphans.len())?;
        }
        for b in &self.bad_files {
            write!(f, "; {}: {}", b.file, b.problem)?;
        }
        Ok(())
    }
}

/// An acquisition session directory, open for writing (or read-only, see [`Session::read`]).
pub struct Session {
    dir: PathBuf,
    manifest: Manifest,
    /// `None`: read-only.
    journal: Option<File>,
    state: State,
    policy: SyncPolicy,
    last_sync: Instant,
    unsynced: bool,
    /// Set when a write failed: the journal's end is unknown.
    poisoned: Option<String>,
    /// Fsyncs for event records, off the caller's thread.
    syncer: Option<syncer::Syncer>,
    /// Extra time every fsync takes, µs ([`Session::simulate_slow_disk`]).
    slow_disk: std::sync::Arc<std::sync::atomic::AtomicU64>,
    /// Hears every record written ([`Session::set_tap`]).
    tap: Option<JournalTap>,
    /// Records this process wrote before a tap was set (the first few), for the tap to hear.
    untapped: Vec<Vec<u8>>,
}

/// Records kept for a tap set late ([`Session::set_tap`]).
const UNTAPPED_KEPT: usize = 64;

/// Hears each record's JSON as it is written to the journal (the live endpoint's feed).
pub type JournalTap = std::sync::Arc<dyn Fn(&[u8]) + Send + Sync>;

impl fmt::Debug for Session {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Session")
            .field("dir", &self.dir)
            .field("session_id", &self.manifest.session_id)
            .field("writable", &self.journal.is_some())
            .field("records", &self.state.records)
            .finish()
    }
}

impl Session {
    /// Creates a session in `dir` (created if absent; it must be empty otherwise): writes
    /// `manifest.json` atomically, then the journal with `SessionStarted`, all fsynced.
    pub fn create(dir: impl AsRef<Path>, manifest: Manifest) -> Result<Session> {
        let dir = dir.as_ref().to_path_buf();
        check_manifest(&manifest).map_err(|detail| SessionError::Refused { detail })?;
        if dir.exists() {
            let leftovers = fs::read_dir(&dir).map_err(io_at(&dir))?;
            for e in leftovers {
                let e = e.map_err(io_at(&dir))?;
                // A create that stopped before its manifest was in place: replaced if a regular
                // file, refused before anything is written if not.
                if e.file_name() != fsutil::partial_path(Path::new(MANIFEST)).as_os_str() {
                    return Err(SessionError::Exists { dir });
                }
                let p = e.path();
                match fsutil::entry(&p)? {
                    fsutil::Entry::File => {}
                    found => return Err(fsutil::foreign(&p, &found, fsutil::REMOVE)),
                }
            }
        } else {
            fs::create_dir_all(&dir).map_err(io_at(&dir))?;
            if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
                fsutil::sync_dir(parent).map_err(io_at(parent))?;
            }
        }
        fsutil::ensure_dirs(&dir, Path::new(FRAMES))?;
        let mut json = serde_json::to_vec_pretty(&manifest).expect("a manifest serializes");
        json.push(b'\n');
        fsutil::write_atomic(&dir.join(MANIFEST), &json)?;
        let (mut session, _) = Self::load(dir, Load::Write { drop_damage: false })?;
        session.sync()?;
        Ok(session)
    }

    /// Opens a session to go on with it: drops a torn or damaged journal tail (saving the
    /// dropped bytes beside the journal), rebuilds the state, removes partly written frame
    /// files, then (unless the session is done) appends `Resumed` and abandons the attempt that
    /// was open.
    /// A journal damaged inside (intact records after the damage) is refused
    /// ([`SessionError::Damaged`]): [`Self::open_dropping_damage`] drops it too.
    pub fn open(dir: impl AsRef<Path>) -> Result<(Session, Recovery)> {
        Self::load(dir.as_ref().to_path_buf(), Load::Write { drop_damage: false })
    }

    /// [`Self::open`] that also drops a journal damaged inside, from its first damaged line on
    /// (the bytes kept in `journal.jsonl.dropped.N`, the count in the `Resumed` record).
    pub fn open_dropping_damage(dir: impl AsRef<Path>) -> Result<(Session, Recovery)> {
        Self::load(dir.as_ref().to_path_buf(), Load::Write { drop_damage: true })
    }

    /// Opens a session for reading only: nothing on disk changes; a damaged tail is ignored
    /// (and reported) but not dropped.
    pub fn read(dir: impl AsRef<Path>) -> Result<(Session, Recovery)> {
        Self::load(dir.as_ref().to_path_buf(), Load::Read)
    }

    /// [`Self::open`] if `dir` holds a manifest, else [`Self::create`] with `manifest`.
    pub fn open_or_create(dir: impl AsRef<Path>, manifest: Manifest) -> Result<(Session, Option<Recovery>)> {
        if dir.as_ref().join(MANIFEST).exists() {
            Self::open(dir).map(|(s, r)| (s, Some(r)))
        } else {
            Self::create(dir, manifest).map(|s| (s, None))
        }
    }

    fn load(dir: PathBuf, how: Load) -> Result<(Session, Recovery)> {
        let write = how != Load::Read;
        // Writing through a link would change files elsewhere (a linked journal truncated, a
        // linked frames/ filled): the session's own files only. (The journal's open below does
        // not follow a link either, whatever is planted meanwhile; a FIFO would block reading.)
        for name in [MANIFEST, JOURNAL, FRAMES] {
            let p = dir.join(name);
            if let found @ (fsutil::Entry::Link(_) | fsutil::Entry::Other) = fsutil::entry(&p)? {
                return Err(fsutil::foreign(&p, &found, fsutil::OWN));
            }
        }
        let manifest = read_manifest(&dir)?;
        let path = dir.join(JOURNAL);
        let file = if write {
            let f = fsutil::open_journal(&path)?;
            // A child process this one spawns holds a copy of the descriptor (and so the lock)
            // between its fork and its exec: a short wait rides that out.
            let deadline = Instant::now() + Duration::from_secs(1);
            while !lock_exclusive(&f).map_err(io_at(&path))? {
                if Instant::now() > deadline {
                    return Err(SessionError::Busy { dir });
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            fsutil::sync_dir(&dir).map_err(io_at(&dir))?;
            Some(f)
        } else {
            match fsutil::open_read(&path) {
                Ok(f) => Some(f),
                Err(e) if e.kind() == io::ErrorKind::NotFound => None,
                Err(e) => match fsutil::entry(&path)? {
                    found @ fsutil::Entry::Link(_) => {
                        return Err(fsutil::foreign(&path, &found, fsutil::OWN))
                    }
                    _ => return Err(io_at(&path)(e)),
                },
            }
        };
        let mut state = State::default();
        let mut recovery = Recovery::default();
        if let Some(f) = &file {
            let end = journal::scan(
                f,
                |line, payload| {
                    let corrupt = |detail: String| SessionError::Corrupt { path: path.clone(), line, detail };
                    let rec: Record = serde_json::from_slice(payload)
                        .map_err(|e| corrupt(format!("not a journal record: {e}")))?;
                    match state.apply(&rec, &manifest) {
                        Ok(true) => Ok(()),
                        Ok(false) => Err(corrupt("an event journaled twice".into())),
                        Err(detail) => Err(corrupt(detail)),
                    }
                },
                io_at(&path),
            )?;
            recovery.records = state.records;
            recovery.dropped_bytes = end.file_len - end.good_len;
            recovery.damage = end.damage;
            recovery.intact_after = end.intact_after;
            if write && recovery.intact_after > 0 && how == (Load::Write { drop_damage: false }) {
                return Err(SessionError::Damaged {
                    path,
                    line: state.records + 1,
                    bytes: recovery.dropped_bytes,
                    intact_after: recovery.intact_after,
                });
            }
            if write && recovery.dropped_bytes > 0 {
                recovery.saved_to = Some(save_tail(&dir, f, end.good_len)?);
                f.set_len(end.good_len).map_err(io_at(&path))?;
                f.sync_all().map_err(io_at(&path))?;
            }
        }
        recovery.interrupted = state.open;
        let mut session = Session {
            dir,
            manifest,
            journal: if write { file } else { None },
            state,
            policy: SyncPolicy::default(),
            last_sync: Instant::now(),
            unsynced: false,
            poisoned: None,
            syncer: None,
            slow_disk: Default::default(),
            tap: None,
            untapped: Vec::new(),
        };
        if let Some(f) = session.journal.as_ref().filter(|_| write) {
            let syncer = syncer::Syncer::new(f.try_clone().map_err(io_at(&session.dir.join(JOURNAL)))?);
            session.slow_disk = syncer.delay();
            session.syncer = Some(syncer);
        }
        session.check_files(write, &mut recovery)?;
        if write && !session.state.done {
            session.upgrade_format()?;
        }
        if write {
            if session.state.records == 0 {
                let id = session.manifest.session_id.clone();
                session.append(&Record::SessionStarted { session_id: id, host_time: now_rfc3339() })?;
            } else if !session.state.done {
                let attempt = session.state.resumes + 1;
                let dropped_bytes = recovery.dropped_bytes;
                session.append(&Record::Resumed { attempt, host_time: now_rfc3339(), dropped_bytes })?;
                if session.state.open.is_some() {
                    session.abandon_step("interrupted: the session stopped before the step was done")?;
                }
            }
        }
        recovery.superseded = session.state.superseded();
        Ok((session, recovery))
    }

    /// Walks `frames/`: removes `.partial` files (when writing), lists orphans, and checks that
    /// the files of completed attempts exist with their recorded size.
    fn check_files(&self, write: bool, recovery: &mut Recovery) -> Result<()> {
        let referenced = self.state.referenced_files();
        let mut files = Vec::new();
        walk(&self.dir, Path::new(FRAMES), &mut files)?;
        for rel in files {
            let name = rel_string(&rel);
            if name.ends_with(PARTIAL_SUFFIX) {
                if write {
                    // Its folders were walked as real ones; checked again right before (one
                    // swapped for a link would have this remove a file elsewhere).
                    fsutil::check_dirs(&self.dir, rel.parent().unwrap_or(Path::new("")))?;
                    let path = self.dir.join(&rel);
                    fs::remove_file(&path).map_err(io_at(&path))?;
                }
                recovery.removed_partials.push(name);
            } else if !referenced.contains(name.as_str()) {
                recovery.orphans.push(name);
            }
        }
        for attempts in self.state.steps.values() {
            for a in attempts.values().filter(|a| a.outcome == Outcome::Done) {
                let files = a.frames.values().map(|f| (&f.file, f.bytes));
                for (file, bytes) in files.chain(a.extra.iter().map(|x| (&x.file, x.bytes))) {
                    if let Some(problem) = self.check_file(file, bytes, None) {
                        recovery.bad_files.push(problem);
                    }
                }
            }
        }
        Ok(())
    }

    fn check_file(&self, file: &str, bytes: u64, crc: Option<u32>) -> Option<FileProblem> {
        let problem = |problem: String| Some(FileProblem { file: file.to_string(), problem });
        let path = self.dir.join(file);
        let len = match fs::metadata(&path) {
            Ok(m) => m.len(),
            Err(e) => return problem(format!("cannot be read: {e}")),
        };
        if len != bytes {
            return problem(format!("{len} bytes, the journal says {bytes}"));
        }
        if let Some(crc) = crc {
            match crc_of_file(&path) {
                Ok(c) if c == crc => {}
                Ok(c) => return problem(format!("CRC-32 {c:08x}, the journal says {crc:08x}")),
                Err(e) => return problem(format!("cannot be read: {e}")),
            }
        }
        None
    }

    /// Reads every file of every completed attempt back and checks its size and CRC-32.
    pub fn verify(&self) -> Vec<FileProblem> {
        let mut out = Vec::new();
        for step in self.state.steps_done() {
            let (_, a) = self.state.done_attempt(step).expect("done");
            let frames = a.frames.values().map(|f| (&f.file, f.bytes, f.crc32));
            for (file, bytes, crc) in frames.chain(a.extra.iter().map(|x| (&x.file, x.bytes, x.crc32))) {
                out.extend(self.check_file(file, bytes, Some(crc)));
            }
        }
        out
    }

    /// The session directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The state rebuilt from the journal.
    pub fn state(&self) -> &State {
        &self.state
    }

    /// Changes when the journal is fsynced.
    pub fn set_sync_policy(&mut self, policy: SyncPolicy) {
        self.policy = policy;
    }

    /// Steps with a completed attempt.
    pub fn steps_done(&self) -> std::collections::BTreeSet<StepId> {
        self.state.steps_done()
    }

    /// The attempt number the next start of `step` gets.
    pub fn next_attempt(&self, step: StepId) -> u32 {
        self.state.next_attempt(step)
    }

    /// The frames of `step`'s completed attempt (empty if it is not done).
    pub fn frames_of(&self, step: StepId) -> Vec<FrameRecord> {
        self.state.frames_of(step)
    }

    /// The frames of `step`'s completed attempt from `camera` only, in frame order.
    pub fn camera_frames_of(&self, step: StepId, camera: u8) -> Vec<FrameRecord> {
        let mut v: Vec<FrameRecord> =
            self.state.frames_of(step).into_iter().filter(|f| f.camera == camera).collect();
        v.sort_by_key(|f| f.frame);
        v
    }

    /// The cameras the plan triggers, in increasing order.
    pub fn cameras(&self) -> Vec<u8> {
        cameras(&self.manifest)
    }

    /// The camera a single-camera pipeline reads: `wanted` if the plan triggers it, else the
    /// plan's only camera, or its lowest one when it has several (the error says which exist).
    pub fn pipeline_camera(&self, wanted: Option<u8>) -> std::result::Result<u8, String> {
        pipeline_camera(&self.manifest, &self.dir, wanted)
    }

    /// The plan's steps not done yet, in plan order (those of `plan`, which may differ from the
    /// manifest's).
    pub fn pending_steps_of(&self, plan: &PlanSummary) -> Vec<StepId> {
        self.state.pending_steps(plan)
    }

    /// The manifest plan's steps not done yet, in plan order.
    pub fn pending_steps(&self) -> Vec<StepId> {
        self.state.pending_steps(&self.manifest.plan)
    }

    /// Going on with a session an older host began: it now holds this format's records, and
    /// its manifest says so.
    fn upgrade_format(&mut self) -> Result<()> {
        if self.manifest.format >= FORMAT_VERSION {
            return Ok(());
        }
        let old = std::mem::replace(&mut self.manifest.format, FORMAT_VERSION);
        let mut json = serde_json::to_vec_pretty(&self.manifest).expect("a manifest serializes");
        json.push(b'\n');
        let written = fsutil::write_atomic(&self.dir.join(MANIFEST), &json);
        if written.is_err() {
            // Not raised on disk: nor are the records it would allow written.
            self.manifest.format = old;
        }
        written
    }

    /// Steps whose completed attempt recorded missing frames, in plan order, with a line saying
    /// what is missing.
    pub fn steps_missing_frames(&self) -> Vec<(StepId, String)> {
        self.manifest
            .plan
            .steps
            .iter()
            .filter_map(|s| {
                let missing = self.state.missing_of(s.id);
                let first = missing.first()?;
                Some((
                    s.id,
                    format!(
                        "{} frame(s) missing (camera {} frame {}: {})",
                        missing.len(),
                        first.camera,
                        first.frame,
                        first.reason
                    ),
                ))
            })
            .collect()
    }

    /// What [`steps_missing_frames`](Self::steps_missing_frames) says, for a person: the steps
    /// with their missing frames and the command that acquires them again; `None` when no
    /// frame is missing.
    pub fn missing_report(&self) -> Option<String> {
        let missing = self.steps_missing_frames();
        if missing.is_empty() {
            return None;
        }
        Some(format!(
            "frames missing in {} step(s):\n{}\nacquire those steps again with `lightrig resume {} --retake-missing`",
            missing.len(),
            missing.iter().map(|(s, why)| format!("  step {s}: {why}")).collect::<Vec<_>>().join("\n"),
            self.dir.display()
        ))
    }

    /// Takes back the completed attempts that recorded missing frames (`StepReopened`), so that
    /// the next run acquires those steps again, and journals the run as a resume. The earlier
    /// attempts' records and files stay, superseded. Returns the steps reopened.
    pub fn reopen_missing(&mut self) -> Result<Vec<StepId>> {
        self.writable()?;
        let steps = self.steps_missing_frames();
        if steps.is_empty() {
            return Ok(Vec::new());
        }
        self.upgrade_format()?;
        for (step, why) in &steps {
            let attempt =
                self.state.done_attempt(*step).map(|(a, _)| a).expect("a step with missing frames is done");
            let reason = format!("retaken: {why}");
            self.append(&Record::StepReopened { step: *step, attempt, reason, host_time: now_rfc3339() })?;
        }
        let attempt = self.state.resumes + 1;
        self.append(&Record::Resumed { attempt, host_time: now_rfc3339(), dropped_bytes: 0 })?;
        Ok(steps.into_iter().map(|(s, _)| s).collect())
    }

    /// `SessionDone` was written.
    pub fn is_done(&self) -> bool {
        self.state.done
    }

    /// The attempt in progress.
    pub fn open_attempt(&self) -> Option<(StepId, u32)> {
        self.state.open
    }

    /// Every paired frame of every completed step, in plan order: the session's frame index.
    pub fn frame_index(&self) -> Vec<FrameRecord> {
        self.manifest.plan.steps.iter().flat_map(|s| self.state.frames_of(s.id)).collect()
    }

    /// Appends one record: checked against the state, written as one line, fsynced per the
    /// [`SyncPolicy`]. `Ok(false)`: an `Event` already journaled, not written again.
    pub fn append(&mut self, rec: &Record) -> Result<bool> {
        self.writable()?;
        if !self.state.check(rec, &self.manifest).map_err(|detail| SessionError::Refused { detail })? {
            return Ok(false);
        }
        let json = serde_json::to_vec(rec).expect("a record serializes");
        let line = encode_line(&json);
        let path = self.dir.join(JOURNAL);
        let file = self.journal.as_mut().expect("writable");
        if let Err(e) = file.write_all(&line) {
            self.poisoned = Some(format!("writing the journal failed: {e}"));
            return Err(io_at(&path)(e));
        }
        self.state.apply(rec, &self.manifest).expect("checked");
        self.unsynced = true;
        match &self.tap {
            Some(tap) => tap(&json),
            None if self.untapped.len() < UNTAPPED_KEPT => self.untapped.push(json),
            None => {}
        }
        let event = matches!(rec, Record::Event { .. });
        if !event {
            self.sync()?;
        } else if self.last_sync.elapsed() >= self.policy.event_interval {
            // Durable within one fsync's time, without waiting for it here.
            match &self.syncer {
                Some(s) => s.request(),
                None => self.sync()?,
            }
            self.last_sync = Instant::now();
        }
        Ok(true)
    }

    /// From now on `tap` hears every record written, as its JSON (what follows the CRC and tab
    /// of its journal line), after it was written; first the records this process wrote
    /// before (opening or creating the session: `SessionStarted`, `Resumed`, …).
    pub fn set_tap(&mut self, tap: Option<JournalTap>) {
        if let Some(t) = &tap {
            for json in self.untapped.drain(..) {
                t(&json);
            }
        }
        self.tap = tap;
    }

    /// Fsyncs the journal: every record appended so far is durable when this returns.
    pub fn sync(&mut self) -> Result<()> {
        if !self.unsynced {
            return Ok(());
        }
        let Some(file) = self.journal.as_ref() else { return Ok(()) };
        syncer::slow_disk(&self.slow_disk);
        if let Err(e) = file.sync_data() {
            // After a failed fsync the kernel may have dropped the dirty pages: what is on disk
            // is unknown.
            self.poisoned = Some(format!("fsync of the journal failed: {e}"));
            return Err(io_at(&self.dir.join(JOURNAL))(e));
        }
        self.unsynced = false;
        self.last_sync = Instant::now();
        Ok(())
    }

    fn writable(&self) -> Result<()> {
        if self.journal.is_none() {
            return Err(SessionError::NotWritable { detail: "opened read-only".into() });
        }
        if let Some(why) = self.syncer.as_ref().and_then(|s| s.failure()) {
            return Err(SessionError::NotWritable {
                detail: format!("{why}; open the session again to recover"),
            });
        }
        if let Some(why) = &self.poisoned {
            return Err(SessionError::NotWritable {
                detail: format!("{why}; open the session again to recover"),
            });
        }
        Ok(())
    }

    /// Journals a device connection.
    pub fn device_connected(&mut self, info: &DeviceInfo) -> Result<()> {
        self.append(&Record::DeviceConnected {
            boot_id: info.boot_id,
            reset_cause: info.reset_cause,
            device: DeviceSummary::from(info),
            host_time: now_rfc3339(),
        })
        .map(|_| ())
    }

    /// Journals a fault the host cleared; `confirmed`: a person's word was needed.
    pub fn fault_cleared(&mut self, boot_id: u32, cause: &FaultCause, confirmed: bool) -> Result<()> {
        let by = if confirmed { "confirmed" } else { "automatic" }.to_string();
        self.append(&Record::FaultCleared { boot_id, cause: *cause, by, host_time: now_rfc3339() })
            .map(|_| ())
    }

    /// Journals a device event; `Ok(false)` if `(boot_id, index)` is journaled already.
    pub fn record_event(&mut self, e: &EventRecord) -> Result<bool> {
        self.append(&Record::Event {
            boot_id: e.boot_id,
            index: e.index,
            host_us: e.host_us,
            event: e.event.clone(),
        })
    }

    /// Starts the next attempt of `step`, run as device sequence `sequence_id`; returns the
    /// attempt number. Durable when it returns.
    pub fn start_step(&mut self, step: StepId, sequence_id: u32) -> Result<u32> {
        let attempt = self.state.next_attempt(step);
        self.append(&Record::StepStarted { step, attempt, sequence_id, host_time: now_rfc3339() })?;
        Ok(attempt)
    }

    /// Records that the open attempt's preparation (`meta.operator`, `meta.host`) was done,
    /// and by whom. Durable when it returns.
    pub fn step_prepared(&mut self, by: &str, actions: Vec<String>) -> Result<()> {
        let (step, attempt) = self.open_or_refuse("StepPrepared")?;
        if self.manifest.format < 2 {
            // A format 1 session (resumed by this host) has no such record.
            return Ok(());
        }
        self.append(&Record::StepPrepared {
            step,
            attempt,
            by: by.into(),
            actions,
            host_time: now_rfc3339(),
        })?;
        Ok(())
    }

    fn open_or_refuse(&self, what: &str) -> Result<(StepId, u32)> {
        self.state.open.ok_or_else(|| SessionError::Refused { detail: format!("{what}: no step is open") })
    }

    /// Stores a paired frame: writes the image to
    /// `frames/step-SSSSSS/attempt-AA/camC-frame-FFFFFF.EXT` (temporary name, fsync, rename,
    /// directory fsync), then appends its `Frame` record (fsynced). A `Frame` record therefore
    /// always names a complete file.
    pub fn store_frame(&mut self, pair: &Pair, ext: &str, data: &[u8]) -> Result<FrameRecord> {
        self.store_frame_stamped(pair, ext, data, None)
    }

    /// [`Self::store_frame`] with the camera's own frame id and timestamp in the record.
    pub fn store_frame_stamped(
        &mut self,
        pair: &Pair,
        ext: &str,
        data: &[u8],
        camera_stamp: Option<CameraStamp>,
    ) -> Result<FrameRecord> {
        let (step, attempt) = self.open_or_refuse("store_frame")?;
        let t = &pair.trigger;
        let file = format!("{}/cam{}-frame-{:06}.{}", attempt_dir(step, attempt), t.camera, t.frame, ext);
        let rec = FrameRecord {
            step,
            attempt,
            camera: t.camera,
            frame: t.frame,
            sequence: t.sequence,
            item: t.item,
            tick: t.tick,
            trigger_us: t.host_us,
            arrived_us: pair.arrived_us,
            late: pair.late,
            file,
            bytes: data.len() as u64,
            crc32: crc32(data),
            camera_stamp,
        };
        let record = Record::Frame(rec);
        self.write_file(&record, ext, data)?;
        let Record::Frame(rec) = record else { unreachable!() };
        Ok(rec)
    }

    /// Stores a frame no trigger accounts for, as
    /// `frames/step-SSSSSS/attempt-AA/extra-NNNN-camC-frame-FFFFFF.EXT`, then its `FrameExtra`
    /// record.
    pub fn store_extra(&mut self, extra: &Extra, ext: &str, data: &[u8]) -> Result<ExtraRecord> {
        let (step, attempt) = self.open_or_refuse("store_extra")?;
        let n = self.state.steps[&step][&attempt].extra.len();
        let file = format!(
            "{}/extra-{n:04}-cam{}-frame-{:06}.{}",
            attempt_dir(step, attempt),
            extra.camera,
            extra.frame,
            ext
        );
        let rec = ExtraRecord {
            step,
            attempt,
            camera: extra.camera,
            frame: extra.frame,
            arrived_us: extra.arrived_us,
            reason: extra.reason,
            file,
            bytes: data.len() as u64,
            crc32: crc32(data),
        };
        let record = Record::FrameExtra(rec);
        self.write_file(&record, ext, data)?;
        let Record::FrameExtra(rec) = record else { unreachable!() };
        Ok(rec)
    }

    fn write_file(&mut self, record: &Record, ext: &str, data: &[u8]) -> Result<()> {
        self.writable()?;
        if ext.is_empty()
            || ext.len() > 16
            || !ext.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit())
        {
            return Err(SessionError::Refused {
                detail: format!("file extension {ext:?}: use 1 to 16 lowercase letters and digits"),
            });
        }
        // Refuse before writing anything.
        self.state.check(record, &self.manifest).map_err(|detail| SessionError::Refused { detail })?;
        let file = match record {
            Record::Frame(f) => &f.file,
            Record::FrameExtra(x) => &x.file,
            _ => unreachable!(),
        };
        // Every folder on the way a real one of the session's, created if missing: checked on
        // every file, as a folder may be replaced by a link while the session is open.
        fsutil::ensure_dirs(&self.dir, Path::new(file).parent().expect("in a folder"))?;
        syncer::slow_disk(&self.slow_disk);
        fsutil::write_atomic(&self.dir.join(file), data)?;
        self.append(record).map(|_| ())
    }

    /// Makes every frame file and every journal fsync take `delay` longer, as on a slow or
    /// busy disk: for tests of what must not stall meanwhile (a real-time device's link).
    pub fn simulate_slow_disk(&mut self, delay: Duration) {
        let us = u64::try_from(delay.as_micros()).unwrap_or(u64::MAX);
        self.slow_disk.store(us, std::sync::atomic::Ordering::Relaxed);
    }

    /// Records a trigger whose frame never came (fsynced).
    pub fn frame_missing(&mut self, trigger: &Trigger, reason: &str) -> Result<MissingRecord> {
        let (step, attempt) = self.open_or_refuse("frame_missing")?;
        let rec = MissingRecord {
            step,
            attempt,
            camera: trigger.camera,
            frame: trigger.frame,
            sequence: trigger.sequence,
            item: trigger.item,
            tick: trigger.tick,
            trigger_us: trigger.host_us,
            reason: reason.to_string(),
        };
        self.append(&Record::FrameMissing(rec.clone()))?;
        Ok(rec)
    }

    /// Completes the open attempt (fsynced); refused unless every trigger the plan expects has
    /// its `Frame` or `FrameMissing`.
    pub fn finish_step(&mut self) -> Result<(StepId, u32)> {
        let (step, attempt) = self.open_or_refuse("finish_step")?;
        let a = &self.state.steps[&step][&attempt];
        let (frames, missing, extra) = (a.frames.len() as u32, a.missing.len() as u32, a.extra.len() as u32);
        self.append(&Record::StepDone {
            step,
            attempt,
            triggers: frames + missing,
            frames,
            missing,
            extra,
            host_time: now_rfc3339(),
        })?;
        Ok((step, attempt))
    }

    /// Abandons the open attempt (a fault, an unplug): the step is acquired again as the next
    /// attempt.
    pub fn abandon_step(&mut self, reason: &str) -> Result<(StepId, u32)> {
        let (step, attempt) = self.open_or_refuse("abandon_step")?;
        self.append(&Record::StepAbandoned {
            step,
            attempt,
            reason: reason.to_string(),
            host_time: now_rfc3339(),
        })?;
        Ok((step, attempt))
    }

    /// Ends the session (every plan step must be done).
    pub fn finish(&mut self) -> Result<()> {
        self.append(&Record::SessionDone { host_time: now_rfc3339() }).map(|_| ())
    }

    /// Deletes the directories of abandoned attempts (their records stay in the journal, naming
    /// files that are gone). Returns the directories removed.
    pub fn remove_superseded(&mut self) -> Result<Vec<PathBuf>> {
        self.writable()?;
        let mut removed = Vec::new();
        for (step, attempt) in self.state.superseded() {
            let rel = attempt_dir(step, attempt);
            // Each folder on the way, and the attempt's own, a real one of the session's:
            // removing through a link would delete files elsewhere.
            if fsutil::check_dirs(&self.dir, Path::new(&rel))? {
                let dir = self.dir.join(rel);
                fs::remove_dir_all(&dir).map_err(io_at(&dir))?;
                let parent = dir.parent().expect("inside the session");
                fsutil::sync_dir(parent).map_err(io_at(parent))?;
                removed.push(dir);
            }
        }
        Ok(removed)
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        if self.poisoned.is_none() {
            let _ = self.sync();
        }
    }
}

/// `frames/step-SSSSSS/attempt-AA`: where an attempt's files go.
pub fn attempt_dir(step: StepId, attempt: u32) -> String {
    format!("{FRAMES}/step-{step:06}/attempt-{attempt:02}")
}

fn check_manifest(m: &Manifest) -> Result<(), String> {
    if m.format != FORMAT_VERSION {
        return Err(format!("manifest format {}, this host writes {FORMAT_VERSION}", m.format));
    }
    check_plan(m)
}

/// What every manifest, of any format this host reads, must hold.
fn check_plan(m: &Manifest) -> Result<(), String> {
    if m.session_id.is_empty() {
        return Err("the manifest has no session id".into());
    }
    let mut ids = HashSet::new();
    for s in &m.plan.steps {
        if !ids.insert(s.id) {
            return Err(format!("plan step id {} appears twice", s.id));
        }
        let mut cams = HashSet::new();
        if let Some(t) = s.triggers.iter().find(|t| !cams.insert(t.camera)) {
            return Err(format!("plan step {} lists camera {} twice", s.id, t.camera));
        }
    }
    Ok(())
}

/// The cameras `manifest`'s plan triggers, in increasing order.
fn cameras(manifest: &Manifest) -> Vec<u8> {
    let mut c: Vec<u8> =
        manifest.plan.steps.iter().flat_map(|s| s.triggers.iter().map(|t| t.camera)).collect();
    c.sort_unstable();
    c.dedup();
    c
}

/// [`Session::pipeline_camera`] of the session in `dir` with `manifest`.
fn pipeline_camera(manifest: &Manifest, dir: &Path, wanted: Option<u8>) -> std::result::Result<u8, String> {
    let cameras = cameras(manifest);
    match (wanted, cameras.first()) {
        (Some(c), _) if cameras.contains(&c) => Ok(c),
        (Some(c), _) => Err(format!(
            "{}: the session has no frames from camera {c} (its cameras: {:?}); pick one of those with --camera",
            dir.display(),
            cameras
        )),
        (None, Some(&c)) => Ok(c),
        (None, None) => Err(format!("{}: the session's plan triggers no camera", dir.display())),
    }
}

fn read_manifest(dir: &Path) -> Result<Manifest> {
    let path = dir.join(MANIFEST);
    let bytes = match fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            return Err(SessionError::NotASession { dir: dir.to_path_buf() })
        }
        Err(e) => return Err(io_at(&path)(e)),
    };
    #[derive(serde::Deserialize)]
    struct Format {
        format: u32,
    }
    let corrupt = |e: serde_json::Error| SessionError::Corrupt {
        path: path.clone(),
        line: 0,
        detail: format!("not a session manifest: {e}"),
    };
    let Format { format } = serde_json::from_slice(&bytes).map_err(corrupt)?;
    if format > FORMAT_VERSION {
        return Err(SessionError::Newer { dir: dir.to_path_buf(), format });
    }
    let m: Manifest = serde_json::from_slice(&bytes).map_err(corrupt)?;
    check_plan(&m).map_err(|detail| SessionError::Corrupt { path: path.clone(), line: 0, detail })?;
    Ok(m)
}

/// How [`Session::load`] opens.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Load {
    Read,
    Write { drop_damage: bool },
}

/// Copies the journal from `from` to its end into `journal.jsonl.dropped.N` (first free N).
fn save_tail(dir: &Path, journal: &File, from: u64) -> Result<PathBuf> {
    let path = dir.join(JOURNAL);
    let mut tail = Vec::new();
    let mut f = journal;
    io::Seek::seek(&mut f, io::SeekFrom::Start(from)).map_err(io_at(&path))?;
    f.read_to_end(&mut tail).map_err(io_at(&path))?;
    let mut n = 1;
    let out = loop {
        let p = dir.join(format!("{JOURNAL}.dropped.{n}"));
        // Anything at the name (an earlier drop's file, a link) is left alone, never written.
        if fsutil::entry(&p)? == fsutil::Entry::Absent {
            break p;
        }
        n += 1;
    };
    fsutil::write_atomic(&out, &tail)?;
    Ok(out)
}

/// Writes `bytes` as the file `name` (a plain file name) of the session in `dir`, atomically
/// and durably, as the session writes its own files: a link or anything but a regular file at
/// `name` or at its temporary name (`name.partial`) is refused ([`SessionError::Foreign`]),
/// never written through. For the files beside the journal that other parts of lightrig keep
/// in a session (a camera's response copy).
pub fn write_session_file(dir: impl AsRef<Path>, name: &str, bytes: &[u8]) -> Result<()> {
    let mut parts = Path::new(name).components();
    if !matches!((parts.next(), parts.next()), (Some(std::path::Component::Normal(_)), None))
        || name.ends_with(PARTIAL_SUFFIX)
        || [MANIFEST, JOURNAL].contains(&name)
    {
        return Err(SessionError::Refused {
            detail: format!("{name:?}: not a name for a file of its own beside the session's journal"),
        });
    }
    fsutil::write_atomic(&dir.as_ref().join(name), bytes)
}

/// Files under `dir/rel`, as paths relative to `dir`.
fn walk(dir: &Path, rel: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let abs = dir.join(rel);
    let entries = match fs::read_dir(&abs) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(io_at(&abs)(e)),
    };
    let mut names = Vec::new();
    for e in entries {
        let e = e.map_err(io_at(&abs))?;
        let kind = e.file_type().map_err(io_at(&abs))?;
        if kind.is_symlink() {
            let path = abs.join(e.file_name());
            let found = fsutil::Entry::Link(fs::read_link(&path).unwrap_or_default());
            return Err(fsutil::foreign(&path, &found, fsutil::OWN));
        }
        names.push((e.file_name(), kind.is_dir()));
    }
    names.sort();
    for (name, is_dir) in names {
        let r = rel.join(name);
        if is_dir {
            walk(dir, &r, out)?;
        } else {
            out.push(r);
        }
    }
    Ok(())
}

fn rel_string(p: &Path) -> String {
    p.components().map(|c| c.as_os_str().to_string_lossy()).collect::<Vec<_>>().join("/")
}

/// Takes the writer's lock: an exclusive advisory lock on the journal (`flock` on Unix,
/// `LockFileEx` on Windows), released when the file is closed or the process dies (however it
/// dies). `Ok(false)`: someone else holds it.
fn lock_exclusive(f: &File) -> io::Result<bool> {
    match f.try_lock() {
        Ok(()) => Ok(true),
        Err(std::fs::TryLockError::WouldBlock) => Ok(false),
        Err(std::fs::TryLockError::Error(e)) => Err(e),
    }
}

/// CRC-32/ISO-HDLC of a file's content.
pub fn crc_of_file(path: &Path) -> io::Result<u32> {
    let mut f = File::open(path)?;
    let mut crc = Crc32::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            return Ok(crc.finish());
        }
        crc.update(&buf[..n]);
    }
}

/// Every record of a session's journal, in order. Stops at the first damaged line, as
/// opening does.
pub fn journal_records(dir: impl AsRef<Path>) -> Result<Vec<Record>> {
    let mut out = Vec::new();
    for_each_record(dir, |rec| out.push(rec))?;
    Ok(out)
}

/// Each record of a session's journal in turn, none kept (a session of a million frames has
/// millions of records). Stops at the first damaged line, as opening does.
pub fn for_each_record(dir: impl AsRef<Path>, mut f: impl FnMut(Record)) -> Result<()> {
    let path = dir.as_ref().join(JOURNAL);
    let file = File::open(&path).map_err(io_at(&path))?;
    journal::scan(
        &file,
        |line, payload| {
            let rec: Record = serde_json::from_slice(payload).map_err(|e| SessionError::Corrupt {
                path: path.clone(),
                line,
                detail: format!("not a journal record: {e}"),
            })?;
            f(rec);
            Ok(())
        },
        io_at(&path),
    )
    .map(|_| ())
}

/// Who prepared each step attempt, in journal order: each `StepPrepared` record's `by`.
pub fn prepared_by(dir: impl AsRef<Path>) -> Result<Vec<String>> {
    Ok(journal_records(dir)?
        .into_iter()
        .filter_map(|r| match r {
            Record::StepPrepared { by, .. } => Some(by),
            _ => None,
        })
        .collect())
}

/// Every trigger event in a session's journal, by `(sequence, item)`: the rig's state at each
/// frame (the frame records name their trigger by these two numbers).
pub fn trigger_events(
    dir: impl AsRef<Path>,
) -> Result<std::collections::HashMap<(u32, u32), lightrig_protocol::event::TriggerEvent>> {
    let mut out = std::collections::HashMap::new();
    for_each_record(dir, |r| {
        if let Record::Event { event: lightrig_protocol::Event::Trigger(t), .. } = r {
            out.insert((t.sequence, t.item), t);
        }
    })?;
    Ok(out)
}
