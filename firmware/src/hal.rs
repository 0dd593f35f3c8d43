//! The hardware the controller drives, as small traits. Board crates implement them for real
//! pins, timers and converters; [`crate::sim`] implements them for the host, recording every
//! change with its tick.
//!
//! Every output call carries `at`, the tick the change belongs to. The controller makes the
//! call once its clock has reached `at` (at most the run loop's wake-up latency later, and
//! never more than 1 ms: see `FaultCause::Late`); a board that wants the edge exactly on `at`
//! despite that latency can latch outputs through a timer compare one slot behind. Levels are
//! electrical (`true` = high): the controller applies each peripheral's configured polarity.
//!
//! Power-on levels are the board's duty: laser enables and camera triggers must come out of
//! reset inactive (pull resistors), before any configuration reaches the controller.

use lightrig_protocol::config::Xy;
use lightrig_protocol::event::Switch;
use lightrig_protocol::sequence::AxisRef;

/// Galvo pairs.
pub trait Galvos {
    /// Drives pair `pair` to `to` (converter codes). An error is a fault of that output.
    fn set_galvo(&mut self, pair: u8, to: Xy, at: u64) -> Result<(), HwError>;
}

/// Laser shutters / TTL enables and their interlock inputs.
pub trait Lasers {
    /// Sets the enable output of `channel` to `level`.
    fn set_laser(&mut self, channel: u8, level: bool, at: u64);
    /// The present level of `channel`'s interlock input.
    fn interlock_level(&mut self, channel: u8) -> bool;
}

/// Step/dir/enable drivers of stepper axes and filter wheels, and their switches.
pub trait Motors {
    /// One step pulse on `motor`.
    fn step(&mut self, motor: AxisRef, at: u64);
    /// Sets the direction output.
    fn set_dir(&mut self, motor: AxisRef, level: bool, at: u64);
    /// Sets the driver-enable output.
    fn set_enable(&mut self, motor: AxisRef, level: bool, at: u64);
    /// The present level of one of `motor`'s switch inputs.
    fn switch_level(&mut self, motor: AxisRef, switch: Switch) -> bool;
}

/// An edge seen on a camera's exposure-active input, time-stamped by the hardware (input
/// capture), so its tick is exact even if the controller reads it later.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Capture {
    /// Camera.
    pub camera: u8,
    /// Level after the edge.
    pub level: bool,
    /// Tick of the edge.
    pub tick: u64,
}

/// Camera trigger outputs and exposure-active inputs.
pub trait Cameras {
    /// Sets the trigger output of `camera` to `level`.
    fn set_trigger(&mut self, camera: u8, level: bool, at: u64);
    /// The oldest captured exposure edge not yet taken, if its tick is at or before `until`.
    fn take_capture(&mut self, until: u64) -> Option<Capture>;
}

/// Voice-coil output streams (DAC or I2S fed by DMA from double buffers).
pub trait VoiceCoils {
    /// Hands over the samples `first_sample..first_sample + samples.len()` of `channel`
    /// (sample 0 is the first after the channel was configured). The stream plays them a fixed
    /// [`crate::rig::VOICE_COIL_LATENCY_BLOCKS`] blocks after their nominal time.
    /// `at` is the tick of the hand-over.
    fn write_samples(&mut self, channel: u8, first_sample: u64, samples: &[i16], at: u64);
    /// The sample rates the outputs can play, inclusive: a configuration outside them is
    /// refused (`voice_coil.sample_rate_hz`). The default is the protocol's whole range.
    fn sample_rates(&self) -> (u32, u32) {
        lightrig_protocol::config::SAMPLE_RATE_RANGE
    }
}

/// The flash slots of a board with a bootloader (embassy-boot's active, update and state
/// partitions: [`crate::boot::BootSlots`]). A board without one keeps the defaults and is not
/// updated over the link (`UpdateError::Unsupported`).
pub trait FirmwareSlots {
    /// Bytes of the active slot: the largest image (0: no update over the link).
    fn active_len(&self) -> u32 {
        0
    }
    /// Where an older image starts in the update slot after a swap (the bootloader's page).
    fn fallback_offset(&self) -> u32 {
        0
    }
    /// Reads the active slot (the running image).
    fn read_active(&mut self, _offset: u32, _buf: &mut [u8]) -> Result<(), SlotError> {
        Err(SlotError::Unsupported)
    }
    /// Reads the update slot.
    fn read_update(&mut self, _offset: u32, _buf: &mut [u8]) -> Result<(), SlotError> {
        Err(SlotError::Unsupported)
    }
    /// Erases the update slot for a new image; refused while the running image is unconfirmed.
    fn erase_update(&mut self) -> Result<(), SlotError> {
        Err(SlotError::Unsupported)
    }
    /// Writes into the erased update slot (`offset` and length multiples of 64).
    fn write_update(&mut self, _offset: u32, _data: &[u8]) -> Result<(), SlotError> {
        Err(SlotError::Unsupported)
    }
    /// Verifies `signature` (ed25519 over the SHA-512 of the update slot's first `len` bytes)
    /// with the board's public key and marks the image to be swapped in at the next reset.
    fn verify_and_mark(&mut self, _len: u32, _signature: &[u8; 64]) -> Result<(), SlotError> {
        Err(SlotError::Unsupported)
    }
    /// Whether the running image was swapped in and not yet confirmed.
    fn unconfirmed(&mut self) -> Result<bool, SlotError> {
        Ok(false)
    }
    /// Keeps the running image (and forgets an image marked for the next reset).
    fn confirm(&mut self) -> Result<(), SlotError> {
        Err(SlotError::Unsupported)
    }
}

/// Why a flash-slot operation failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SlotError {
    /// The board has no slots.
    Unsupported,
    /// The running image is not confirmed: no new update before it is.
    Unconfirmed,
    /// The signature does not verify.
    BadSignature,
    /// The flash refused the operation.
    Flash,
}

/// Everything a board provides.
pub trait Board: Galvos + Lasers + Motors + Cameras + VoiceCoils + FirmwareSlots {}

impl<T: Galvos + Lasers + Motors + Cameras + VoiceCoils + FirmwareSlots> Board for T {}

/// A peripheral reported a failure (SPI error, driver fault).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HwError;
