//! A session read for processing one step at a time: memory that does not grow with the
//! session's frames.
//!
//! [`Session::read`](super::Session::read) keeps every frame record (~0.5 kB a frame: 0.5 GB for
//! the million frames of the paper's DISCO horse). [`SessionIndex::read`] checks the journal as
//! opening does, record by record, but keeps of each completed attempt only where its records lie
//! in the journal (a byte range) and its counts; [`SessionIndex::step`] reads one step's records
//! and trigger events back from that range. A step is bounded by the plan (the shipped DISCO plan's
//! largest is 12 289 frames), the session is not.
//!
//! What reading does not do here: list orphan files or stat every frame file (opening does); a
//! pipeline reads each file anyway and says which one is short or unreadable.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use lightrig_protocol::event::TriggerEvent;
use lightrig_protocol::Event;

use super::journal::{decode_line, scan};
use super::records::{ExtraRecord, FrameRecord, Manifest, MissingRecord, Record, StepId};
use super::state::{Outcome, State};
use super::{io_at, read_manifest, Result, SessionError, JOURNAL};

/// What a step's records read back no longer matching the index means, and what to do.
const CHANGED: &str = "the journal changed after the session was read: read it again";

/// Where one attempt's records lie in the journal, and what it holds.
#[derive(Debug, Clone, PartialEq)]
struct AttemptSpan {
    attempt: u32,
    /// Journal bytes from its `StepStarted` line to the end of its last line so far.
    start: u64,
    end: u64,
    /// Paired frames per camera.
    frames: BTreeMap<u8, u32>,
}

/// A session's journal checked and indexed, its records left on disk (see the module's docs).
#[derive(Debug)]
pub struct SessionIndex {
    dir: PathBuf,
    manifest: Manifest,
    done: bool,
    /// Each done step's completed attempt.
    steps: BTreeMap<StepId, AttemptSpan>,
}

/// One completed attempt's records, read back from the journal.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StepRecords {
    /// Paired frames, by camera, then frame number.
    pub frames: Vec<FrameRecord>,
    /// Missing frames, by camera, then frame number.
    pub missing: Vec<MissingRecord>,
    /// Extra frames, in journal order.
    pub extra: Vec<ExtraRecord>,
    /// The trigger events journaled during the attempt, by `(sequence, item)`.
    pub triggers: HashMap<(u32, u32), TriggerEvent>,
}

impl StepRecords {
    /// The frames from `camera`, in frame order.
    pub fn camera_frames(&self, camera: u8) -> impl Iterator<Item = &FrameRecord> {
        self.frames.iter().filter(move |f| f.camera == camera)
    }

    /// The trigger event a frame was paired with.
    pub fn trigger_of(&self, f: &FrameRecord) -> Option<&TriggerEvent> {
        self.triggers.get(&(f.sequence, f.item))
    }
}

impl SessionIndex {
    /// Reads and checks `dir`'s manifest and journal (as [`Session::read`](super::Session::read)
    /// does: a damaged tail is ignored, a record that breaks the history is an error, and so is
    /// damage that intact lines follow: [`SessionError::Damaged`]), keeping
    /// per step attempt only its place in the journal and its counts.
    pub fn read(dir: impl AsRef<Path>) -> Result<SessionIndex> {
        let dir = dir.as_ref().to_path_buf();
        let manifest = read_manifest(&dir)?;
        let path = dir.join(JOURNAL);
        let mut state = State::default();
        let mut spans: HashMap<(StepId, u32), AttemptSpan> = HashMap::new();
        match File::open(&path) {
            Ok(file) => {
                let mut offset = 0u64;
                let mut lines = 0usize;
                let end = scan(
                    &file,
                    |line, payload| {
                        let corrupt =
                            |detail: String| SessionError::Corrupt { path: path.clone(), line, detail };
                        lines = line;
                        let rec: Record = serde_json::from_slice(payload)
                            .map_err(|e| corrupt(format!("not a journal record: {e}")))?;
                        match state.apply(&rec, &manifest) {
                            Ok(true) => {}
                            Ok(false) => return Err(corrupt("an event journaled twice".into())),
                            Err(detail) => return Err(corrupt(detail)),
                        }
                        // A committed line is its 8-digit CRC, a tab, the payload and a line feed.
                        let start = offset;
                        offset += payload.len() as u64 + 10;
                        if let Record::StepStarted { step, attempt, .. } = &rec {
                            let span = AttemptSpan {
                                attempt: *attempt,
                                start,
                                end: offset,
                                frames: BTreeMap::new(),
                            };
                            spans.insert((*step, *attempt), span);
                        }
                        if let Some((step, attempt)) = state.open {
                            if let Some(span) = spans.get_mut(&(step, attempt)) {
                                span.end = offset;
                                if let Record::Frame(f) = &rec {
                                    *span.frames.entry(f.camera).or_default() += 1;
                                }
                            }
                        }
                        // The attempt just ended: its records stay on disk, not in the state.
                        if let Record::StepDone { step, attempt, .. }
                        | Record::StepAbandoned { step, attempt, .. } = &rec
                        {
                            if let Some(span) = spans.get_mut(&(*step, *attempt)) {
                                span.end = offset;
                            }
                            if let Some(a) = state.steps.get_mut(step).and_then(|s| s.get_mut(attempt)) {
                                a.frames.clear();
                                a.missing.clear();
                                a.extra.clear();
                            }
                        }
                        Ok(())
                    },
                    io_at(&path),
                )?;
                // Damage with intact lines after it is not a torn last write: reading on would
                // drop the session's later records unseen.
                if end.intact_after > 0 {
                    return Err(SessionError::Damaged {
                        path,
                        line: lines as u64 + 1,
                        bytes: end.file_len - end.good_len,
                        intact_after: end.intact_after,
                    });
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_at(&path)(e)),
        }
        let steps = state
            .steps
            .iter()
            .filter_map(|(&step, attempts)| {
                let (&n, _) = attempts.iter().rev().find(|(_, a)| a.outcome == Outcome::Done)?;
                Some((step, spans.remove(&(step, n))?))
            })
            .collect();
        Ok(SessionIndex { dir, manifest, done: state.done, steps })
    }

    /// The session directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// `SessionDone` was written.
    pub fn is_done(&self) -> bool {
        self.done
    }

    /// The camera a single-camera pipeline reads (see
    /// [`Session::pipeline_camera`](super::Session::pipeline_camera)).
    pub fn pipeline_camera(&self, wanted: Option<u8>) -> std::result::Result<u8, String> {
        super::pipeline_camera(&self.manifest, &self.dir, wanted)
    }

    /// The completed attempt of `step`, if it is done.
    pub fn done_attempt(&self, step: StepId) -> Option<u32> {
        self.steps.get(&step).map(|s| s.attempt)
    }

    /// Paired frames from `camera` in `step`'s completed attempt (0 if the step is not done).
    pub fn frame_count(&self, step: StepId, camera: u8) -> u32 {
        self.steps.get(&step).and_then(|s| s.frames.get(&camera)).copied().unwrap_or(0)
    }

    /// `step`'s completed attempt's records, read back from the journal (empty if the step is not
    /// done). An error if the journal changed since [`Self::read`].
    pub fn step(&self, step: StepId) -> Result<StepRecords> {
        let mut out = StepRecords::default();
        let Some(span) = self.steps.get(&step) else { return Ok(out) };
        let path = self.dir.join(JOURNAL);
        let mut file = File::open(&path).map_err(io_at(&path))?;
        file.seek(SeekFrom::Start(span.start)).map_err(io_at(&path))?;
        let mut reader = BufReader::with_capacity(1 << 16, file.take(span.end - span.start));
        let mut line = Vec::new();
        let changed = |detail: String| SessionError::Corrupt {
            path: path.clone(),
            line: 0,
            detail: format!("step {step}'s records from byte {}: {detail}; {CHANGED}", span.start),
        };
        let (mut first, mut read) = (true, 0u64);
        loop {
            line.clear();
            let n = reader.read_until(b'\n', &mut line).map_err(io_at(&path))?;
            if n == 0 {
                break;
            }
            read += n as u64;
            let payload = decode_line(&line).map_err(|d| changed(d.describe().to_string()))?;
            let rec: Record =
                serde_json::from_slice(payload).map_err(|e| changed(format!("not a journal record: {e}")))?;
            let ours = |s: StepId, a: u32| s == step && a == span.attempt;
            match rec {
                Record::StepStarted { step: s, attempt: a, .. } if first && ours(s, a) => {}
                _ if first => return Err(changed("not the step's StepStarted".into())),
                Record::Frame(f) if ours(f.step, f.attempt) => out.frames.push(f),
                Record::FrameMissing(m) if ours(m.step, m.attempt) => out.missing.push(m),
                Record::FrameExtra(x) if ours(x.step, x.attempt) => out.extra.push(x),
                Record::Event { event: Event::Trigger(t), .. } => {
                    out.triggers.insert((t.sequence, t.item), t);
                }
                _ => {}
            }
            first = false;
        }
        if read != span.end - span.start {
            return Err(changed(format!("{read} of the step's {} bytes", span.end - span.start)));
        }
        out.frames.sort_by_key(|f| (f.camera, f.frame));
        out.missing.sort_by_key(|m| (m.camera, m.frame));
        Ok(out)
    }
}
