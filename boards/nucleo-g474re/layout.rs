// The NUCLEO-G474RE's flash layout (512 KiB at 0x0800_0000, dual-bank 2 KiB pages), shared by
// the bootloader, the firmware and both build scripts (`include!`d). Every boundary is a
// multiple of 4 KiB, so it is page-aligned in either bank mode. embassy-boot needs the update
// (DFU) partition one page larger than the active one.

/// Address of the flash's first byte.
pub const FLASH_BASE: u32 = 0x0800_0000;
/// The bootloader: swaps images at reset, then jumps to the active partition.
pub const BOOTLOADER: (u32, u32) = (0x0000_0000, 24 * 1024);
/// embassy-boot's state: the marks and the swap's progress.
pub const STATE: (u32, u32) = (0x0000_6000, 8 * 1024);
/// The running firmware (the application is linked here).
pub const ACTIVE: (u32, u32) = (0x0000_8000, 232 * 1024);
/// The update slot: a new image is written here, the old one kept here after a swap.
pub const DFU: (u32, u32) = (0x0004_2000, 236 * 1024);
/// RAM for both (SRAM1 + SRAM2 + CCM SRAM, contiguous at 0x2000_0000).
pub const RAM: (u32, u32) = (0x2000_0000, 128 * 1024);
