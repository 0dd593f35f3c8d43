//! A board's flash slots through `embassy-boot` (feature `boot`): its firmware updater writes
//! and marks the update slot, its bootloader swaps it in at reset, power-fail safe, and swaps
//! the old image back if the new one was not confirmed. Generic over `embedded-storage`'s
//! [`NorFlash`]: the MCU's flash partitions on a board, [`crate::memflash::MemFlash`] on the
//! host.

use embassy_boot::{
    BlockingFirmwareState, BlockingFirmwareUpdater, BootLoader, BootLoaderConfig, FirmwareUpdaterConfig,
    FirmwareUpdaterError, State,
};
use embedded_storage::nor_flash::NorFlash;

use crate::hal::{FirmwareSlots, SlotError};

/// Scratch for embassy-boot, aligned for any flash's writes.
#[repr(align(32))]
struct Aligned([u8; 64]);

/// The active, update and state partitions, and the public key images are signed for.
pub struct BootSlots<A, D, S> {
    /// Active partition: the running image.
    pub active: A,
    /// Update (DFU) partition: at least one page larger than the active one.
    pub dfu: D,
    /// State partition: the bootloader's marks and swap progress.
    pub state: S,
    key: [u8; 32],
}

fn updater_err(e: FirmwareUpdaterError) -> SlotError {
    match e {
        FirmwareUpdaterError::Flash(_) => SlotError::Flash,
        FirmwareUpdaterError::Signature(_) => SlotError::BadSignature,
        FirmwareUpdaterError::BadState => SlotError::Unconfirmed,
    }
}

impl<A: NorFlash, D: NorFlash, S: NorFlash> BootSlots<A, D, S> {
    /// The partitions, with the ed25519 public key images must be signed with.
    pub fn new(active: A, dfu: D, state: S, public_key: [u8; 32]) -> Self {
        BootSlots { active, dfu, state, key: public_key }
    }

    /// The bootloader's page: the larger erase size of the two image partitions.
    pub const PAGE: u32 =
        if A::ERASE_SIZE > D::ERASE_SIZE { A::ERASE_SIZE as u32 } else { D::ERASE_SIZE as u32 };

    /// What the bootloader does at reset: swaps a marked image in, or the old one back if
    /// the last swapped-in image was not confirmed. Power-fail safe: cut at any write, the
    /// next reset goes on where it stopped.
    pub fn boot(&mut self) -> Result<State, SlotError> {
        let mut buf = Aligned([0; 64]);
        // Pages are copied in pieces of the scratch's length: as long as the page allows.
        let unit = S::WRITE_SIZE.max(A::WRITE_SIZE).max(D::WRITE_SIZE);
        let len = if Self::PAGE.is_multiple_of(64) && 64usize.is_multiple_of(unit) { 64 } else { unit };
        let config =
            BootLoaderConfig { active: &mut self.active, dfu: &mut self.dfu, state: &mut self.state };
        BootLoader::new(config).prepare_boot(&mut buf.0[..len]).map_err(|_| SlotError::Flash)
    }

    fn with_updater<T>(
        &mut self,
        f: impl FnOnce(
            &mut BlockingFirmwareUpdater<'_, &mut D, &mut S>,
            &[u8; 32],
        ) -> Result<T, FirmwareUpdaterError>,
    ) -> Result<T, SlotError> {
        let mut buf = Aligned([0; 64]);
        let config = FirmwareUpdaterConfig { dfu: &mut self.dfu, state: &mut self.state };
        let mut u = BlockingFirmwareUpdater::new(config, &mut buf.0[..S::WRITE_SIZE]);
        f(&mut u, &self.key).map_err(updater_err)
    }

    fn state(&mut self) -> Result<State, SlotError> {
        let mut buf = Aligned([0; 64]);
        BlockingFirmwareState::new(&mut self.state, &mut buf.0[..S::WRITE_SIZE])
            .get_state()
            .map_err(updater_err)
    }
}

impl<A: NorFlash, D: NorFlash, S: NorFlash> FirmwareSlots for BootSlots<A, D, S> {
    fn active_len(&self) -> u32 {
        self.active.capacity() as u32
    }

    fn fallback_offset(&self) -> u32 {
        Self::PAGE
    }

    fn read_active(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.active.read(offset, buf).map_err(|_| SlotError::Flash)
    }

    fn read_update(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), SlotError> {
        self.dfu.read(offset, buf).map_err(|_| SlotError::Flash)
    }

    fn erase_update(&mut self) -> Result<(), SlotError> {
        self.with_updater(|u, _| u.prepare_update().map(|_| ()))
    }

    fn write_update(&mut self, offset: u32, data: &[u8]) -> Result<(), SlotError> {
        self.dfu.write(offset, data).map_err(|_| SlotError::Flash)
    }

    fn verify_and_mark(&mut self, len: u32, signature: &[u8; 64]) -> Result<(), SlotError> {
        self.with_updater(|u, key| u.verify_and_mark_updated(key, signature, len))
    }

    fn unconfirmed(&mut self) -> Result<bool, SlotError> {
        Ok(self.state()? == State::Swap)
    }

    fn confirm(&mut self) -> Result<(), SlotError> {
        self.with_updater(|u, _| u.mark_booted())
    }
}
