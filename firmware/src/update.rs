//! Firmware update over the link, the device's side: the update commands as a state machine
//! over the board's [`FirmwareSlots`]. The bootloader (embassy-boot) does the swap and the
//! rollback at the next reset; this decides what is written and when an image is marked.
//!
//! Nothing is written for an image built for another board or too large for the slot; bytes
//! are written strictly in order (a chunk the device already has is acknowledged again, so a
//! host that lost an answer or was unplugged goes on where the device stands); the image is
//! marked only when the stored trailer is the one announced and the signature verifies.

use lightrig_protocol::session::BoardId;
use lightrig_protocol::update::TRAILER_LEN;
use lightrig_protocol::update::{
    ImageInfo, UpdateCommand, UpdateError, UpdatePhase, UpdateStatus, UPDATE_CHUNK,
};

use crate::hal::{FirmwareSlots, SlotError};

/// The update in progress, if any: `Idle`, `Receiving` or `Ready` (`Unconfirmed` is the
/// slots' state, never held here).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Updater {
    phase: Phase,
}

type Phase = UpdatePhase;

impl Default for Updater {
    fn default() -> Self {
        Updater { phase: Phase::Idle }
    }
}

fn slot_err(e: SlotError) -> UpdateError {
    match e {
        SlotError::Unsupported => UpdateError::Unsupported,
        SlotError::Unconfirmed => UpdateError::Unconfirmed,
        SlotError::BadSignature => UpdateError::BadSignature,
        SlotError::Flash => UpdateError::Flash,
    }
}

impl Updater {
    /// An update begun and not finished or cancelled: nothing may move or light meanwhile.
    pub fn in_progress(&self) -> bool {
        self.phase != Phase::Idle
    }

    /// An image received, checked and marked: the next reset swaps it in.
    pub fn ready(&self) -> bool {
        matches!(self.phase, Phase::Ready { .. })
    }

    /// Carries out `cmd` on `slots` for a device that is a `board`.
    pub fn handle<S: FirmwareSlots + ?Sized>(
        &mut self,
        cmd: &UpdateCommand,
        slots: &mut S,
        board: BoardId,
    ) -> Result<UpdateStatus, UpdateError> {
        match cmd {
            UpdateCommand::Status => {}
            UpdateCommand::Begin(image) => self.begin(image, slots, board)?,
            UpdateCommand::Write { offset, data } => self.write(*offset, data, slots)?,
            UpdateCommand::Finish(sig) => self.finish(&sig.to_bytes(), slots)?,
            UpdateCommand::Cancel => match self.phase {
                Phase::Idle | Phase::Unconfirmed => return Err(UpdateError::NotBegun),
                Phase::Receiving { .. } => self.phase = Phase::Idle,
                Phase::Ready { .. } => {
                    // The image is marked for the swap: writing the "booted" mark over it
                    // unmarks it.
                    slots.confirm().map_err(slot_err)?;
                    self.phase = Phase::Idle;
                }
            },
            UpdateCommand::Confirm => {
                if !slots.unconfirmed().map_err(slot_err)? {
                    return Err(UpdateError::NothingToConfirm);
                }
                slots.confirm().map_err(slot_err)?;
            }
        }
        Ok(self.status(slots))
    }

    /// Whether `Begin(image)` would be refused for the board or the image itself (no slots,
    /// another board, too large): checked before anything is stopped or erased.
    pub fn check_begin<S: FirmwareSlots + ?Sized>(
        image: &ImageInfo,
        slots: &S,
        board: BoardId,
    ) -> Result<(), UpdateError> {
        let slot = slots.active_len();
        if slot == 0 {
            return Err(UpdateError::Unsupported);
        }
        if image.board != board {
            return Err(UpdateError::WrongBoard { image: image.board, device: board });
        }
        if image.signed_len() > slot || image.code_len == 0 {
            return Err(UpdateError::TooLarge { image: image.signed_len(), slot });
        }
        Ok(())
    }

    fn begin<S: FirmwareSlots + ?Sized>(
        &mut self,
        image: &ImageInfo,
        slots: &mut S,
        board: BoardId,
    ) -> Result<(), UpdateError> {
        Self::check_begin(image, slots, board)?;
        if let Phase::Receiving { image: going, .. } = self.phase {
            if going == *image {
                // The same image: go on where the transfer stopped.
                return Ok(());
            }
        }
        if slots.unconfirmed().map_err(slot_err)? {
            return Err(UpdateError::Unconfirmed);
        }
        if let Phase::Ready { .. } = self.phase {
            // Another image replaces the one marked: unmark it first.
            slots.confirm().map_err(slot_err)?;
        }
        self.phase = Phase::Idle;
        slots.erase_update().map_err(slot_err)?;
        self.phase = Phase::Receiving { image: *image, received: 0 };
        Ok(())
    }

    fn write<S: FirmwareSlots + ?Sized>(
        &mut self,
        offset: u32,
        data: &[u8],
        slots: &mut S,
    ) -> Result<(), UpdateError> {
        let Phase::Receiving { image, received } = self.phase else { return Err(UpdateError::NotBegun) };
        let end = offset.saturating_add(data.len() as u32);
        if offset < received && end <= received {
            // A retransmission of what the device has.
            return Ok(());
        }
        // Whole chunks (the last one shorter, ending the image): every write stays aligned to
        // the flash's write size.
        let whole = data.len() == UPDATE_CHUNK || end == image.signed_len();
        if offset != received || end > image.signed_len() || !whole || data.is_empty() {
            return Err(UpdateError::OutOfOrder { expected: received });
        }
        slots.write_update(offset, data).map_err(slot_err)?;
        self.phase = Phase::Receiving { image, received: end };
        Ok(())
    }

    fn finish<S: FirmwareSlots + ?Sized>(
        &mut self,
        signature: &[u8; 64],
        slots: &mut S,
    ) -> Result<(), UpdateError> {
        let Phase::Receiving { image, received } = self.phase else { return Err(UpdateError::NotBegun) };
        if received != image.signed_len() {
            return Err(UpdateError::Incomplete { received });
        }
        // Whatever fails from here, the bytes received are of no use: the next Begin starts
        // afresh.
        self.phase = Phase::Idle;
        let mut trailer = [0u8; TRAILER_LEN];
        slots.read_update(image.trailer_at(), &mut trailer).map_err(slot_err)?;
        if ImageInfo::from_trailer(&trailer) != Some(image) {
            return Err(UpdateError::TrailerMismatch);
        }
        slots.verify_and_mark(image.signed_len(), signature).map_err(slot_err)?;
        self.phase = Phase::Ready { image };
        Ok(())
    }

    /// Where the update stands, with the images the slots hold.
    pub fn status<S: FirmwareSlots + ?Sized>(&self, slots: &mut S) -> UpdateStatus {
        let slot = slots.active_len();
        let unconfirmed = slots.unconfirmed().unwrap_or(false);
        let phase = match self.phase {
            Phase::Idle if unconfirmed => UpdatePhase::Unconfirmed,
            other => other,
        };
        let running = find(slot, |at, buf| slots.read_active(at, buf).is_ok());
        // The update slot holds the image before the last swap only while no new one is being
        // written over it.
        let fallback = if self.phase == Phase::Idle {
            let from = slots.fallback_offset();
            find(slot, |at, buf| slots.read_update(from + at, buf).is_ok())
        } else {
            None
        };
        UpdateStatus { phase, running, fallback, slot }
    }
}

/// [`ImageInfo::find`], skipping the work when the slot is empty.
fn find(len: u32, mut read: impl FnMut(u32, &mut [u8]) -> bool) -> Option<ImageInfo> {
    if len == 0 {
        return None;
    }
    ImageInfo::find(len, &mut read)
}
