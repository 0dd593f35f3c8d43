//! The emulated board's flash: a file on the host (`flash=PATH` on the semihosting command
//! line), reached through semihosting, so its contents survive a reset of the emulated MCU and
//! a restart of QEMU. It behaves as NOR flash: an erase sets a 4 KiB page to 0xFF, a write can
//! only clear bits. The update slots (embassy-boot's active, update and state partitions) lie
//! in it; without `flash=` the board has none and is not updated over the link.
//!
//! `cut=N` cuts the power at the Nth erase or write of the bootloader's swap: QEMU exits there,
//! as a board whose supply fails, and the harness starts it again.
//!
//! Shared by the firmware and the bootloader (boards/qemu-mps2-an386-bootloader), so it logs
//! nothing (the two would mix their defmt streams).

use core::cell::RefCell;

use cortex_m_semihosting::syscall;
use embassy_embedded_hal::flash::partition::BlockingPartition;
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embedded_storage::nor_flash::{ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash};
use lightrig_firmware::boards::DEVELOPMENT_PUBLIC_KEY;
use lightrig_firmware::boot::BootSlots;

pub use lightrig_firmware::boards::qemu_flash::{ACTIVE, DFU, FILE_LEN, STATE};
/// Erase page.
pub const PAGE: usize = lightrig_firmware::boards::qemu_flash::PAGE as usize;

/// A flash operation the host refused (the file is gone, or shorter than the layout).
#[derive(Debug, Clone, Copy)]
pub struct FileError;

impl NorFlashError for FileError {
    fn kind(&self) -> NorFlashErrorKind {
        NorFlashErrorKind::Other
    }
}

/// The flash file, open for reading and writing.
pub struct FileFlash {
    fd: usize,
    /// Erases and writes so far while `cut` is armed.
    ops: u32,
    /// Cut the power at this operation (the bootloader arms it).
    pub cut: Option<u32>,
}

impl FileFlash {
    /// Opens `path` (`r+b`: it must exist; the harness makes it, as a factory programs a board).
    pub fn open(path: &[u8]) -> Option<Self> {
        let mut name = [0u8; 128];
        let name = name.get_mut(..path.len() + 1)?;
        name[..path.len()].copy_from_slice(path);
        // SAFETY: SYS_OPEN reads the NUL-terminated name of the given length.
        let fd = unsafe { syscall!(OPEN, name.as_ptr(), 3usize, path.len()) } as isize;
        if fd < 0 {
            return None;
        }
        // SAFETY: SYS_FLEN takes the descriptor only.
        let len = unsafe { syscall!(FLEN, fd as usize) } as isize;
        if len < FILE_LEN as isize {
            return None;
        }
        Some(Self { fd: fd as usize, ops: 0, cut: None })
    }

    fn seek(&self, offset: u32) -> Result<(), FileError> {
        // SAFETY: SYS_SEEK takes the descriptor and an absolute position.
        let r = unsafe { syscall!(SEEK, self.fd, offset as usize) };
        if r == 0 {
            Ok(())
        } else {
            Err(FileError)
        }
    }

    fn read_at(&self, offset: u32, buf: &mut [u8]) -> Result<(), FileError> {
        self.seek(offset)?;
        // SAFETY: SYS_READ writes at most `len` bytes into `buf`; it returns the bytes not read.
        let left = unsafe { syscall!(READ, self.fd, buf.as_mut_ptr(), buf.len()) };
        if left == 0 {
            Ok(())
        } else {
            Err(FileError)
        }
    }

    fn write_at(&self, offset: u32, buf: &[u8]) -> Result<(), FileError> {
        self.seek(offset)?;
        // SAFETY: SYS_WRITE reads `len` bytes from `buf`; it returns the bytes not written.
        let left = unsafe { syscall!(WRITE, self.fd, buf.as_ptr(), buf.len()) };
        if left == 0 {
            Ok(())
        } else {
            Err(FileError)
        }
    }

    /// Counts an erase or write; at the armed count the power goes.
    fn operation(&mut self) {
        if let Some(n) = self.cut {
            self.ops += 1;
            if self.ops >= n {
                cortex_m_semihosting::debug::exit(cortex_m_semihosting::debug::EXIT_FAILURE);
                // Nothing more is written, whatever the emulator does.
                #[allow(clippy::empty_loop)]
                loop {}
            }
        }
    }
}

impl ErrorType for FileFlash {
    type Error = FileError;
}

impl ReadNorFlash for FileFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), FileError> {
        self.read_at(offset, bytes)
    }

    fn capacity(&self) -> usize {
        FILE_LEN as usize
    }
}

impl NorFlash for FileFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = PAGE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), FileError> {
        let ones = [0xFFu8; 256];
        let mut at = from;
        while at < to {
            self.operation();
            let n = (to - at).min(ones.len() as u32);
            self.write_at(at, &ones[..n as usize])?;
            at += n;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), FileError> {
        self.operation();
        // NOR: a write clears bits, it never sets them.
        let mut old = [0u8; 256];
        for (k, chunk) in bytes.chunks(old.len()).enumerate() {
            let at = offset + (k * old.len()) as u32;
            let old = &mut old[..chunk.len()];
            self.read_at(at, old)?;
            for (o, &n) in old.iter_mut().zip(chunk) {
                *o &= n;
            }
            self.write_at(at, old)?;
        }
        Ok(())
    }
}

pub type Part = BlockingPartition<'static, NoopRawMutex, FileFlash>;
pub type Slots = BootSlots<Part, Part, Part>;

/// The slots in the flash file, trusting the development key (images signed with
/// `lightrig flash sign --virtual-key`).
pub fn slots(flash: &'static Mutex<NoopRawMutex, RefCell<FileFlash>>) -> Slots {
    BootSlots::new(
        BlockingPartition::new(flash, ACTIVE.0, ACTIVE.1),
        BlockingPartition::new(flash, DFU.0, DFU.1),
        BlockingPartition::new(flash, STATE.0, STATE.1),
        DEVELOPMENT_PUBLIC_KEY,
    )
}
