//! The sequence buffer: chunk ordering, credit and the schedule of the next item. Executing an
//! item is the rig's job ([`super::Rig`]); this keeps the bookkeeping that decides *when*.
//!
//! Rules (see `docs/protocol.md`, "Sequences"):
//! - chunk 0 opens a sequence (and drops any sequence loaded but not started); chunks follow
//!   in order; a chunk marked `last` closes it;
//! - a chunk is accepted whole or not at all, and only if it fits the free slots;
//! - item `i` is due `delta` ticks after item `i-1` was due (after the start tick for item 0,
//!   after the moment its condition held for the item following a `Wait`);
//! - running out of items before the last chunk is an underrun.

use heapless::Deque;
use lightrig_protocol::sequence::{BufferStatus, Chunk, Item, WaitFor};
use lightrig_protocol::{Error, MAX_CAMERAS};

/// Item slots in the sequence buffer (the host's credit when the buffer is empty).
pub const SEQUENCE_BUFFER: usize = 256;

/// Where the sequence stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Phase {
    /// Nothing loaded.
    Idle,
    /// Chunks are arriving; not started.
    Loaded,
    /// Executing.
    Running,
}

/// A `Wait` item in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Waiting {
    pub until: WaitFor,
    /// The tick at which not holding is a fault.
    pub deadline: u64,
    /// Index of the `Wait` item.
    pub item: u32,
}

pub(crate) struct Sequencer {
    pub id: u32,
    pub phase: Phase,
    next_chunk: u32,
    /// The chunk marked `last` has arrived.
    pub complete: bool,
    buffer: Deque<Item, SEQUENCE_BUFFER>,
    /// Items executed (the index of the next one).
    pub executed: u32,
    /// Due tick of the last executed item (or the start tick).
    pub last_due: u64,
    pub waiting: Option<Waiting>,
    /// Triggers per camera since the start: the next frame number.
    pub frames: [u32; MAX_CAMERAS],
    /// Free slots at the last `Buffer` event.
    reported_free: u16,
}

impl Sequencer {
    pub const fn new() -> Self {
        Self {
            id: 0,
            phase: Phase::Idle,
            next_chunk: 0,
            complete: false,
            buffer: Deque::new(),
            executed: 0,
            last_due: 0,
            waiting: None,
            frames: [0; MAX_CAMERAS],
            reported_free: SEQUENCE_BUFFER as u16,
        }
    }

    pub fn status(&self) -> BufferStatus {
        BufferStatus {
            sequence: self.id,
            capacity: SEQUENCE_BUFFER as u16,
            free: self.free(),
            next_chunk: self.next_chunk,
            executed: self.executed,
        }
    }

    pub fn free(&self) -> u16 {
        (SEQUENCE_BUFFER - self.buffer.len()) as u16
    }

    /// Checks that `chunk` may be appended now (order, credit), without changing anything.
    pub fn check_chunk(&self, chunk: &Chunk) -> Result<(), Error> {
        let expected = if chunk.chunk == 0 {
            if self.phase == Phase::Running {
                // A running sequence only takes its own next chunk.
                return Err(Error::ChunkOutOfOrder { sequence: self.id, expected: self.next_chunk });
            }
            0
        } else {
            if self.phase == Phase::Idle || chunk.sequence != self.id || self.complete {
                return Err(Error::ChunkOutOfOrder { sequence: self.id, expected: self.next_chunk });
            }
            self.next_chunk
        };
        if chunk.chunk != expected {
            return Err(Error::ChunkOutOfOrder { sequence: self.id, expected });
        }
        let free = if chunk.chunk == 0 { SEQUENCE_BUFFER as u16 } else { self.free() };
        if chunk.items.len() > usize::from(free) {
            return Err(Error::BufferFull { free });
        }
        Ok(())
    }

    /// Appends a chunk that passed [`Self::check_chunk`] and the rig's item checks.
    pub fn append(&mut self, chunk: &Chunk) {
        if chunk.chunk == 0 {
            *self = Self::new();
            self.id = chunk.sequence;
            self.phase = Phase::Loaded;
        }
        for item in &chunk.items {
            // Cannot fail: `check_chunk` compared the length with the free slots.
            let _ = self.buffer.push_back(item.clone());
        }
        self.next_chunk = self.next_chunk.saturating_add(1);
        self.complete = chunk.last;
        self.reported_free = self.free();
    }

    /// The buffered items, next first.
    pub fn items(&self) -> impl Iterator<Item = &Item> {
        self.buffer.iter()
    }

    /// Starts the loaded sequence with item 0 due `delta` after `start`.
    pub fn start(&mut self, start: u64) {
        self.phase = Phase::Running;
        self.last_due = start;
        self.executed = 0;
        self.waiting = None;
        self.frames = [0; MAX_CAMERAS];
    }

    /// Due tick of the next item, if it is buffered and not held by a `Wait`.
    pub fn next_due(&self) -> Option<u64> {
        if self.phase != Phase::Running || self.waiting.is_some() {
            return None;
        }
        self.buffer.front().map(|item| self.last_due.saturating_add(u64::from(item.delta)))
    }

    /// Nothing buffered while running.
    pub fn is_dry(&self) -> bool {
        self.phase == Phase::Running && self.waiting.is_none() && self.buffer.is_empty()
    }

    /// Takes the next item, due at `due`.
    pub fn pop(&mut self, due: u64) -> Option<(u32, Item)> {
        let item = self.buffer.pop_front()?;
        self.last_due = due;
        let index = self.executed;
        self.executed = self.executed.saturating_add(1);
        Some((index, item))
    }

    /// Drops the sequence (finished, aborted or faulted).
    pub fn clear(&mut self) {
        self.buffer.clear();
        self.phase = Phase::Idle;
        self.waiting = None;
        self.complete = false;
        self.next_chunk = 0;
    }

    /// Whether the buffer has drained enough since the last report to be worth a `Buffer`
    /// event: a quarter of its capacity, or all of it. Keeps the event rate far below the item
    /// rate while the host always learns of new credit in time.
    pub fn take_report(&mut self) -> Option<BufferStatus> {
        let free = self.free();
        let step = (SEQUENCE_BUFFER / 4) as u16;
        let drained = free.saturating_sub(self.reported_free);
        if drained >= step || (drained > 0 && free as usize == SEQUENCE_BUFFER) {
            self.reported_free = free;
            return Some(self.status());
        }
        None
    }
}
