//! A NOR flash in memory (feature `std`): the virtual board's partitions and the update tests'.
//! Like the real thing, erasing sets a whole sector to `0xFF` and writing can only clear bits;
//! its contents are shared between clones (they survive the virtual board's resets), and a
//! power cut can be arranged after any number of writes and erases, for every partition of one
//! chip at once ([`MemFlash::on_same_chip`]).

use std::sync::{Arc, Mutex};

use embedded_storage::nor_flash::{ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash};

/// `SIZE` bytes erased in sectors of `ERASE` bytes, written in units of `WRITE` bytes.
#[derive(Debug, Clone)]
pub struct MemFlash<const ERASE: usize, const WRITE: usize> {
    inner: Arc<Mutex<Inner>>,
    power: Arc<Mutex<Power>>,
}

#[derive(Debug)]
struct Inner {
    mem: Vec<u8>,
}

/// The chip's power, shared by its partitions.
#[derive(Debug, Default)]
struct Power {
    /// Write and erase calls left before the power goes (`None`: it stays on).
    budget: Option<u64>,
    /// Write and erase calls done.
    ops: u64,
}

/// A flash operation refused: out of bounds, misaligned, or the power went.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MemFlashError {
    /// Outside the flash.
    OutOfBounds,
    /// Not on a write or erase boundary.
    NotAligned,
    /// The power was cut ([`MemFlash::cut_after`]): nothing more is written.
    PowerCut,
}

impl NorFlashError for MemFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            MemFlashError::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            MemFlashError::NotAligned => NorFlashErrorKind::NotAligned,
            MemFlashError::PowerCut => NorFlashErrorKind::Other,
        }
    }
}

impl<const ERASE: usize, const WRITE: usize> MemFlash<ERASE, WRITE> {
    /// `size` bytes, erased.
    pub fn new(size: usize) -> Self {
        assert!(size.is_multiple_of(ERASE), "a whole number of sectors");
        let power = Arc::new(Mutex::new(Power::default()));
        MemFlash { inner: Arc::new(Mutex::new(Inner { mem: vec![0xFF; size] })), power }
    }

    /// Another partition of `size` bytes on the same chip: one power for both.
    pub fn on_same_chip<const E: usize, const W: usize>(&self, size: usize) -> MemFlash<E, W> {
        let mut other = MemFlash::<E, W>::new(size);
        other.power = Arc::clone(&self.power);
        other
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn power(&self) -> std::sync::MutexGuard<'_, Power> {
        self.power.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The chip's power goes after `ops` more write and erase calls (`None`: never); a call
    /// that finds it gone changes nothing.
    pub fn cut_after(&self, ops: Option<u64>) {
        self.power().budget = ops;
    }

    /// Write and erase calls done on the chip so far.
    pub fn ops(&self) -> u64 {
        self.power().ops
    }

    /// A copy of the contents.
    pub fn contents(&self) -> Vec<u8> {
        self.lock().mem.clone()
    }

    /// Overwrites the contents, bypassing the flash's rules (what a debug probe does).
    pub fn program(&self, offset: usize, bytes: &[u8]) {
        self.lock().mem[offset..offset + bytes.len()].copy_from_slice(bytes);
    }

    fn spend(&self) -> Result<(), MemFlashError> {
        let mut p = self.power();
        if let Some(b) = p.budget.as_mut() {
            if *b == 0 {
                return Err(MemFlashError::PowerCut);
            }
            *b -= 1;
        }
        p.ops += 1;
        Ok(())
    }
}

impl<const ERASE: usize, const WRITE: usize> ErrorType for MemFlash<ERASE, WRITE> {
    type Error = MemFlashError;
}

impl<const ERASE: usize, const WRITE: usize> ReadNorFlash for MemFlash<ERASE, WRITE> {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        let inner = self.lock();
        let at = offset as usize;
        let src = inner.mem.get(at..at + bytes.len()).ok_or(MemFlashError::OutOfBounds)?;
        bytes.copy_from_slice(src);
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.lock().mem.len()
    }
}

impl<const ERASE: usize, const WRITE: usize> NorFlash for MemFlash<ERASE, WRITE> {
    const WRITE_SIZE: usize = WRITE;
    const ERASE_SIZE: usize = ERASE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let (from, to) = (from as usize, to as usize);
        if !from.is_multiple_of(ERASE) || !to.is_multiple_of(ERASE) || from > to {
            return Err(MemFlashError::NotAligned);
        }
        if to > self.lock().mem.len() {
            return Err(MemFlashError::OutOfBounds);
        }
        // Sector by sector: a cut leaves the earlier sectors erased.
        for sector in (from..to).step_by(ERASE) {
            self.spend()?;
            self.lock().mem[sector..sector + ERASE].fill(0xFF);
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let at = offset as usize;
        if !at.is_multiple_of(WRITE) || !bytes.len().is_multiple_of(WRITE) {
            return Err(MemFlashError::NotAligned);
        }
        if at + bytes.len() > self.lock().mem.len() {
            return Err(MemFlashError::OutOfBounds);
        }
        self.spend()?;
        // A write can only clear bits, as on NOR flash.
        let mut inner = self.lock();
        for (d, s) in inner.mem[at..at + bytes.len()].iter_mut().zip(bytes) {
            *d &= *s;
        }
        Ok(())
    }
}
