//! A session's frames read back in plan order, each with the trigger it was paired with and its
//! decoded image: what the Python package (`python/`) iterates, and what its reading benchmark
//! compares it with.
//!
//! One step's records are in memory at a time ([`SessionIndex::step`]), and one frame's pixels
//! per [`Frames::next`]: a session of any size streams.

use std::collections::VecDeque;
use std::sync::Arc;

use lightrig_imaging::io::{decode, Encoding, Image, ReadOptions};
use lightrig_protocol::event::TriggerEvent;

use super::index::SessionIndex;
use super::journal::crc32;
use super::records::{FrameRecord, StepId};
use super::{io_at, Result, SessionError};

/// A frame read back.
#[derive(Debug, Clone)]
pub struct ReadFrame {
    /// Its journal record.
    pub record: FrameRecord,
    /// The trigger it was paired with (`None` only in a journal whose trigger event is lost).
    pub trigger: Option<TriggerEvent>,
    /// Its pixels: integer data as stored, normalised (8-bit `/255`, 16-bit `/65535`), linear.
    pub image: Image,
    /// Bits per sample on disk: 8, 16 (integer or half) or 32 (float).
    pub bits: u8,
}

impl SessionIndex {
    /// The steps with a completed attempt, in plan order.
    pub fn done_steps(&self) -> Vec<StepId> {
        self.manifest()
            .plan
            .steps
            .iter()
            .map(|s| s.id)
            .filter(|&id| self.done_attempt(id).is_some())
            .collect()
    }

    /// Reads `f`'s file, checks its length and CRC against the record and decodes it (integer
    /// data read as linear levels: a camera's raw output). An error names the file and the step.
    pub fn read_frame(&self, f: &FrameRecord) -> Result<(Image, u8)> {
        let path = self.dir().join(&f.file);
        let bytes = std::fs::read(&path).map_err(io_at(&path))?;
        let damaged = |detail: String| SessionError::Corrupt {
            path: path.clone(),
            line: 0,
            detail: format!(
                "frame {} of camera {} in step {}: {detail}; `lightrig resume --retake-missing` cannot \
                 replace a damaged file: take the step again or restore the file from a copy",
                f.frame, f.camera, f.step
            ),
        };
        if bytes.len() as u64 != f.bytes {
            return Err(damaged(format!("{} bytes on disk, the journal says {}", bytes.len(), f.bytes)));
        }
        let crc = crc32(&bytes);
        if crc != f.crc32 {
            return Err(damaged(format!("CRC-32 {crc:08x}, the journal says {:08x}", f.crc32)));
        }
        decode(&bytes, &path, ReadOptions { assume: Encoding::Linear, expect_depth: None })
            .map_err(|e| damaged(format!("cannot be decoded: {e}")))
    }

    /// An error naming the plan's steps if the plan has no step `step`.
    pub fn check_step(&self, step: StepId) -> Result<()> {
        if self.manifest().step(step).is_some() {
            return Ok(());
        }
        let ids: Vec<String> = self.manifest().plan.steps.iter().map(|s| s.id.to_string()).collect();
        Err(SessionError::Refused {
            detail: format!(
                "{}: the plan has no step {step} (its steps: {})",
                self.dir().display(),
                ids.join(", ")
            ),
        })
    }

    /// The frames of `steps` (every completed step in plan order if `None`) from `camera` (every
    /// camera if `None`), read one at a time.
    pub fn frames(self: &Arc<Self>, steps: Option<Vec<StepId>>, camera: Option<u8>) -> Result<Frames> {
        let steps = match steps {
            None => self.done_steps(),
            Some(steps) => {
                steps.iter().try_for_each(|&s| self.check_step(s))?;
                steps
            }
        };
        Ok(Frames { index: Arc::clone(self), steps: steps.into(), camera, queue: VecDeque::new() })
    }
}

/// Frames read one at a time ([`SessionIndex::frames`]): each step's records are read when its
/// first frame is reached.
#[derive(Debug)]
pub struct Frames {
    index: Arc<SessionIndex>,
    steps: VecDeque<StepId>,
    camera: Option<u8>,
    queue: VecDeque<(FrameRecord, Option<TriggerEvent>)>,
}

impl Frames {
    /// The next frame's record and trigger, without decoding it (`None` at the end).
    pub fn next_record(&mut self) -> Result<Option<(FrameRecord, Option<TriggerEvent>)>> {
        while self.queue.is_empty() {
            let Some(step) = self.steps.pop_front() else { return Ok(None) };
            let records = self.index.step(step)?;
            let camera = self.camera;
            self.queue = records
                .frames
                .iter()
                .filter(|f| camera.is_none_or(|c| c == f.camera))
                .map(|f| (f.clone(), records.trigger_of(f).cloned()))
                .collect();
        }
        Ok(self.queue.pop_front())
    }
}

impl Iterator for Frames {
    type Item = Result<ReadFrame>;

    fn next(&mut self) -> Option<Self::Item> {
        match self.next_record() {
            Ok(None) => None,
            Err(e) => Some(Err(e)),
            Ok(Some((record, trigger))) => {
                Some(self.index.read_frame(&record).map(|(image, bits)| ReadFrame {
                    record,
                    trigger,
                    image,
                    bits,
                }))
            }
        }
    }
}
