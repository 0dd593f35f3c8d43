//! The session's state, rebuilt from the journal record by record.
//!
//! Every record is checked against the state before it is applied (by the writer before it is
//! written, and again when the journal is read back), so a journal only ever holds a consistent
//! history: one open attempt at a time, each trigger answered once, a step done only when every
//! trigger its plan step expects is answered.

use std::collections::{BTreeMap, BTreeSet};

use super::records::{ExtraRecord, FrameRecord, Manifest, MissingRecord, PlanSummary, Record, StepId};

/// How an attempt at a step ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// Started, not ended (at most one attempt of a session is open).
    Open,
    /// `StepDone`: complete.
    Done,
    /// `StepAbandoned`, or a completed attempt taken back by `StepReopened`: superseded by a
    /// later attempt.
    Abandoned {
        /// Why.
        reason: String,
    },
}

/// One attempt at a step.
#[derive(Debug, Clone, PartialEq)]
pub struct Attempt {
    /// The device sequence id it ran as.
    pub sequence_id: u32,
    /// Paired frames by (camera, frame number).
    pub frames: BTreeMap<(u8, u32), FrameRecord>,
    /// Missing frames by (camera, frame number).
    pub missing: BTreeMap<(u8, u32), MissingRecord>,
    /// Extra frames, in journal order.
    pub extra: Vec<ExtraRecord>,
    /// How it ended.
    pub outcome: Outcome,
}

/// Everything the journal says, in a form that answers questions.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct State {
    /// Records applied.
    pub records: u64,
    /// From `SessionStarted`.
    pub session_id: Option<String>,
    /// `Resumed` records so far.
    pub resumes: u32,
    /// Every attempt of every step, by step and attempt number.
    pub steps: BTreeMap<StepId, BTreeMap<u32, Attempt>>,
    /// The attempt started and not yet done or abandoned.
    pub open: Option<(StepId, u32)>,
    /// Highest event index journaled per device boot id.
    pub last_event: BTreeMap<u32, u32>,
    /// `Event` records.
    pub events: u64,
    /// Boot id of the last `DeviceConnected`.
    pub boot_id: Option<u32>,
    /// `SessionDone` was written.
    pub done: bool,
}

impl State {
    /// Checks `rec` against the state and applies it. `Ok(false)`: an event already journaled
    /// (same boot id, index not above the highest seen), not applied. On `Err` nothing changed.
    pub fn apply(&mut self, rec: &Record, manifest: &Manifest) -> Result<bool, String> {
        if !self.check(rec, manifest)? {
            return Ok(false);
        }
        self.commit(rec);
        Ok(true)
    }

    /// Checks `rec` without applying it: `Ok(false)` for a duplicate event.
    pub fn check(&self, rec: &Record, manifest: &Manifest) -> Result<bool, String> {
        if self.records == 0 && !matches!(rec, Record::SessionStarted { .. }) {
            return Err(format!("the journal must start with SessionStarted, not {}", rec.kind()));
        }
        if self.done && !matches!(rec, Record::StepReopened { .. }) {
            return Err(format!("{} after SessionDone: the session is complete", rec.kind()));
        }
        match rec {
            Record::SessionStarted { session_id, .. } => {
                if self.records != 0 {
                    return Err("a second SessionStarted".into());
                }
                if *session_id != manifest.session_id {
                    return Err(format!(
                        "SessionStarted names session {session_id}, the manifest {}",
                        manifest.session_id
                    ));
                }
            }
            Record::Resumed { attempt, .. } => {
                if *attempt != self.resumes + 1 {
                    return Err(format!("Resumed attempt {attempt}, expected {}", self.resumes + 1));
                }
            }
            Record::DeviceConnected { .. } | Record::FaultCleared { .. } => {}
            Record::StepStarted { step, attempt, .. } => {
                if let Some((s, a)) = self.open {
                    return Err(format!(
                        "StepStarted for step {step} while attempt {a} of step {s} is open; finish or \
                         abandon it first"
                    ));
                }
                if manifest.step(*step).is_none() {
                    return Err(format!("step {step} is not in the plan"));
                }
                if self.steps_done().contains(step) {
                    return Err(format!("step {step} is already done"));
                }
                if *attempt != self.next_attempt(*step) {
                    return Err(format!(
                        "StepStarted attempt {attempt} of step {step}, expected {}",
                        self.next_attempt(*step)
                    ));
                }
            }
            Record::Event { boot_id, index, .. } => {
                return Ok(self.last_event.get(boot_id).is_none_or(|last| index > last));
            }
            Record::Frame(f) => {
                self.check_answer(f.step, f.attempt, f.camera, f.frame, manifest, "Frame")?;
                check_frame_file(&f.file, f.step, f.attempt)?;
            }
            Record::FrameMissing(m) => {
                self.check_answer(m.step, m.attempt, m.camera, m.frame, manifest, "FrameMissing")?;
            }
            Record::FrameExtra(x) => {
                self.check_open(x.step, x.attempt, "FrameExtra")?;
                check_frame_file(&x.file, x.step, x.attempt)?;
            }
            Record::StepPrepared { step, attempt, .. } => {
                self.check_open(*step, *attempt, "StepPrepared")?;
            }
            Record::StepDone { step, attempt, triggers, frames, missing, extra, .. } => {
                let a = self.check_open(*step, *attempt, "StepDone")?;
                let counts = (a.frames.len() as u32, a.missing.len() as u32, a.extra.len() as u32);
                if (*frames, *missing, *extra) != counts {
                    return Err(format!(
                        "StepDone of step {step} attempt {attempt} counts {frames} frames, {missing} \
                         missing, {extra} extra; the journal has {}, {}, {}",
                        counts.0, counts.1, counts.2
                    ));
                }
                if *triggers != frames + missing {
                    return Err(format!("StepDone of step {step}: triggers {triggers} != frames + missing"));
                }
                let plan = manifest.step(*step).expect("checked at StepStarted");
                for t in &plan.triggers {
                    let answered =
                        a.frames.keys().chain(a.missing.keys()).filter(|k| k.0 == t.camera).count();
                    if answered as u32 != plan.expected(t.camera) {
                        return Err(format!(
                            "step {step} attempt {attempt}: camera {} has {answered} of its {} triggers \
                             answered (Frame or FrameMissing); record the rest, or abandon the attempt",
                            t.camera,
                            plan.expected(t.camera)
                        ));
                    }
                }
            }
            Record::StepAbandoned { step, attempt, .. } => {
                self.check_open(*step, *attempt, "StepAbandoned")?;
            }
            Record::StepReopened { step, attempt, .. } => {
                if let Some((s, a)) = self.open {
                    return Err(format!("StepReopened of step {step} while attempt {a} of step {s} is open"));
                }
                match self.done_attempt(*step) {
                    Some((done, _)) if done == *attempt => {}
                    Some((done, _)) => {
                        return Err(format!(
                            "StepReopened of step {step} attempt {attempt}: its completed attempt is {done}"
                        ))
                    }
                    None => return Err(format!("StepReopened of step {step}: the step is not done")),
                }
            }
            Record::SessionDone { .. } => {
                if let Some((s, a)) = self.open {
                    return Err(format!("SessionDone while attempt {a} of step {s} is open"));
                }
                let pending = self.pending_steps(&manifest.plan);
                if !pending.is_empty() {
                    return Err(format!("SessionDone with steps not done: {pending:?}"));
                }
            }
        }
        Ok(true)
    }

    fn check_open(&self, step: StepId, attempt: u32, kind: &str) -> Result<&Attempt, String> {
        if self.open != Some((step, attempt)) {
            return Err(match self.open {
                Some((s, a)) => format!(
                    "{kind} for step {step} attempt {attempt}, but the open one is step {s} attempt {a}"
                ),
                None => format!("{kind} for step {step} attempt {attempt}, but no attempt is open"),
            });
        }
        Ok(&self.steps[&step][&attempt])
    }

    fn check_answer(
        &self,
        step: StepId,
        attempt: u32,
        camera: u8,
        frame: u32,
        manifest: &Manifest,
        kind: &str,
    ) -> Result<(), String> {
        let a = self.check_open(step, attempt, kind)?;
        let key = (camera, frame);
        if a.frames.contains_key(&key) || a.missing.contains_key(&key) {
            return Err(format!(
                "{kind}: step {step} attempt {attempt} already answered camera {camera} frame {frame}"
            ));
        }
        let expected = manifest.step(step).map_or(0, |p| p.expected(camera));
        if frame >= expected {
            return Err(format!(
                "{kind}: camera {camera} frame {frame} is outside step {step}'s plan ({expected} triggers); \
                 record it as FrameExtra"
            ));
        }
        Ok(())
    }

    /// Applies a record [`Self::check`] accepted.
    fn commit(&mut self, rec: &Record) {
        self.records += 1;
        match rec {
            Record::SessionStarted { session_id, .. } => self.session_id = Some(session_id.clone()),
            Record::Resumed { attempt, .. } => self.resumes = *attempt,
            Record::DeviceConnected { boot_id, .. } => self.boot_id = Some(*boot_id),
            Record::StepStarted { step, attempt, sequence_id, .. } => {
                let a = Attempt {
                    sequence_id: *sequence_id,
                    frames: BTreeMap::new(),
                    missing: BTreeMap::new(),
                    extra: Vec::new(),
                    outcome: Outcome::Open,
                };
                self.steps.entry(*step).or_default().insert(*attempt, a);
                self.open = Some((*step, *attempt));
            }
            Record::Event { boot_id, index, .. } => {
                self.last_event.insert(*boot_id, *index);
                self.events += 1;
            }
            Record::Frame(f) => {
                self.attempt_mut(f.step, f.attempt).frames.insert((f.camera, f.frame), f.clone());
            }
            Record::FrameMissing(m) => {
                self.attempt_mut(m.step, m.attempt).missing.insert((m.camera, m.frame), m.clone());
            }
            Record::FrameExtra(x) => self.attempt_mut(x.step, x.attempt).extra.push(x.clone()),
            Record::StepPrepared { .. } | Record::FaultCleared { .. } => {}
            Record::StepDone { step, attempt, .. } => {
                self.attempt_mut(*step, *attempt).outcome = Outcome::Done;
                self.open = None;
            }
            Record::StepAbandoned { step, attempt, reason, .. } => {
                self.attempt_mut(*step, *attempt).outcome = Outcome::Abandoned { reason: reason.clone() };
                self.open = None;
            }
            Record::StepReopened { step, attempt, reason, .. } => {
                self.attempt_mut(*step, *attempt).outcome = Outcome::Abandoned { reason: reason.clone() };
                self.done = false;
            }
            Record::SessionDone { .. } => self.done = true,
        }
    }

    fn attempt_mut(&mut self, step: StepId, attempt: u32) -> &mut Attempt {
        self.steps.get_mut(&step).and_then(|s| s.get_mut(&attempt)).expect("checked")
    }

    /// Steps with a completed attempt.
    pub fn steps_done(&self) -> BTreeSet<StepId> {
        self.steps
            .iter()
            .filter(|(_, attempts)| attempts.values().any(|a| a.outcome == Outcome::Done))
            .map(|(s, _)| *s)
            .collect()
    }

    /// The attempt number the next `StepStarted` of `step` must carry: 1, or one more than the
    /// last attempt journaled.
    pub fn next_attempt(&self, step: StepId) -> u32 {
        self.steps.get(&step).and_then(|a| a.keys().next_back()).map_or(1, |a| a + 1)
    }

    /// The completed attempt of `step` (the latest, should there be several).
    pub fn done_attempt(&self, step: StepId) -> Option<(u32, &Attempt)> {
        self.steps.get(&step)?.iter().rev().find(|(_, a)| a.outcome == Outcome::Done).map(|(n, a)| (*n, a))
    }

    /// The frames of `step`'s completed attempt, by camera and frame number; empty if the step
    /// is not done.
    pub fn frames_of(&self, step: StepId) -> Vec<FrameRecord> {
        self.done_attempt(step).map(|(_, a)| a.frames.values().cloned().collect()).unwrap_or_default()
    }

    /// The missing frames of `step`'s completed attempt.
    pub fn missing_of(&self, step: StepId) -> Vec<MissingRecord> {
        self.done_attempt(step).map(|(_, a)| a.missing.values().cloned().collect()).unwrap_or_default()
    }

    /// The extra frames of `step`'s completed attempt.
    pub fn extra_of(&self, step: StepId) -> Vec<ExtraRecord> {
        self.done_attempt(step).map(|(_, a)| a.extra.clone()).unwrap_or_default()
    }

    /// The plan's steps not yet done, in plan order.
    pub fn pending_steps(&self, plan: &PlanSummary) -> Vec<StepId> {
        let done = self.steps_done();
        plan.steps.iter().map(|s| s.id).filter(|id| !done.contains(id)).collect()
    }

    /// Attempts neither done nor open: their records and files are superseded.
    pub fn superseded(&self) -> Vec<(StepId, u32)> {
        self.steps
            .iter()
            .flat_map(|(s, attempts)| {
                attempts
                    .iter()
                    .filter(|(_, a)| matches!(a.outcome, Outcome::Abandoned { .. }))
                    .map(|(n, _)| (*s, *n))
            })
            .collect()
    }

    /// Every file a `Frame` or `FrameExtra` record names, in any attempt.
    pub fn referenced_files(&self) -> BTreeSet<&str> {
        self.steps
            .values()
            .flat_map(|attempts| attempts.values())
            .flat_map(|a| {
                a.frames.values().map(|f| f.file.as_str()).chain(a.extra.iter().map(|x| x.file.as_str()))
            })
            .collect()
    }
}

/// A record's `file` must lie in its attempt's own folder, `frames/step-SSSSSS/attempt-AA/`,
/// as one plain file name: never an absolute path, `..`, or a path elsewhere, which a reader
/// would otherwise follow out of the session.
fn check_frame_file(file: &str, step: StepId, attempt: u32) -> Result<(), String> {
    let dir = super::attempt_dir(step, attempt);
    let name = file.strip_prefix(&dir).and_then(|rest| rest.strip_prefix('/'));
    let plain = name.is_some_and(|n| {
        !n.is_empty() && n != "." && n != ".." && !n.contains(['/', '\\', '\0']) && !n.starts_with('.')
    });
    if plain {
        Ok(())
    } else {
        Err(format!("file {file:?} is not a file of its attempt's folder {dir}/"))
    }
}
